"""Stage 4, K → reconstruction → report: pycolmap mapping (incremental or global) and bundle
adjustment from the estimate, the estimate written into a copy of an existing model, the ``run``
workflow and its report, and the Open3D view of a model.
"""
