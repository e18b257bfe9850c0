"""Stage 1, images → COLMAP database → snapshot: SIFT features and matching through pycolmap,
the read-only snapshot of keypoints and verified matches, camera models, and the safe write of K.
"""
