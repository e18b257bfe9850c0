"""Baselines to compare with: Mendonça and Cipolla's self-calibration from fundamental
matrices (``fundamental``, ``essential_cost``).
"""
