"""Stage 2, snapshot → triplets → trifocal tensors: three-view tracks, triplet selection,
robust tensor estimation and the projective bundle adjustment that refines each tensor.
"""
