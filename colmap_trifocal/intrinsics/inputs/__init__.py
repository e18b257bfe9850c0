"""A camera's input, database contents → what the stages read: its prior and undistorted keypoints
(``camera_input``), where the start comes from (``prior``), its triplets and three-view
tracks (``triplet_selection``).
"""
