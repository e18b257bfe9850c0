"""The lens: a radial warp where the raw tracks' tensors disagree (``search``, ``warp``), and
the stored model's distortion adjusted from the agreeing triplets (``distortion``,
``fit_statistics``).
"""
