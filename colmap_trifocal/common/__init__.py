"""Shared plumbing used by every stage: errors, the package logger, atomic files, worker pools.

Takes nothing from the other stages and gives them CalibrationError, logger, map_jobs.
"""
