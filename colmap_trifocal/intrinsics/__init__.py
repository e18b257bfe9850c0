"""Stage 3, tensors → K: focal search, the 15 trifocal constraints solved per camera
(Direct / MSAC / MSAC-Opt, FundamentalCalib baseline) per physical camera (a group of camera
ids), observability and uncertainty.
"""
