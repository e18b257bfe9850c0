"""Synthetic scenes with known K (cube, motions, synthetic COLMAP databases) and the demo.

Takes intrinsics and a motion, gives DatabaseContents or a database file plus ground truth.
"""
