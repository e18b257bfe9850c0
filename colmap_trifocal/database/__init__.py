"""Stage 1, images → COLMAP database → snapshot: SIFT features and matching through pycolmap,
the read-only snapshot of keypoints and verified matches, camera models, the grouping of camera
ids into physical cameras (COLMAP's default makes one camera per image), and the safe write of K;
a COLMAP model read as the same input (its tracks as matches), its files checked first.
"""
