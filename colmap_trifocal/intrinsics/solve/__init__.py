"""The mathematics of the solve, shared by every stage: pixels ↔ θ ↔ M (``theta``), the 15
constraints whitened (``whitening``) and solved by Direct / MSAC / MSAC-Opt
(``constraints``), what the images determine and the fallback for the rest
(``observability``, ``parametrization``, ``fallback``), the jackknife and the
combined information (``uncertainty``).
"""
