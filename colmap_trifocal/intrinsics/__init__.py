"""Stage 3, tensors → K, per physical camera (a group of camera ids): the TrifocalCalib
calibration as a list of stages (``pipeline``) over the sub-packages in the order data
flows (``solve`` first, the mathematics every stage uses; then ``inputs``, ``start``,
``tensors``, ``polish``, ``lens``, ``assess``; ``baselines``), with the options and
results they share (``options``, ``results``) and the public entry (``api``).
"""
