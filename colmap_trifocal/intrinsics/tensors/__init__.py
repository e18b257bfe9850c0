"""Tensors and their solve from start to start: one robust tensor per triplet at a start,
reused between starts within one budget per camera (``estimator``), and the attempts:
the solve, the restart, second starts, other starts, the hold (``attempts``).
"""
