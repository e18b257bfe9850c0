"""The polish, the constraint estimate → the triplets' calibrated bundle adjustment where
better supported (``stage``): the shared-camera engine (``shared_camera``,
``camera_setup``, ``calibrated_tracks``), each triplet's Schur complement
(``information``), the adjustment and its prediction (``bundle``).
"""
