"""Where the tensors start: the focal search over calibrated three-view hypotheses
(``focal_search``) and the start candidates, their held values and other starts
(``candidates``).
"""
