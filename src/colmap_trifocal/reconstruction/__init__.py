"""Stage 4, K → reconstruction → report: pycolmap mapping and bundle adjustment from the
estimate, the ``run`` workflow and its report, and the Open3D view of a model.
"""
