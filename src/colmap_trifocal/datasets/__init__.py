"""Readers of datasets with ground-truth intrinsics."""
