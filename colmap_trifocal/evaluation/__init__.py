"""The paper's evaluation: real datasets with ground truth and the synthetic experiment.

Its public names (``__all__``, what the notebooks use): :class:`EvaluationOptions` and
:func:`evaluate_scene` (the protocol on one scene), :func:`run_synthetic_case` (one run
of the synthetic experiment), :func:`write_outputs` (the CSV, Markdown table and
boxplots; the plots need the extra ``viz``).
"""

from .protocol import EvaluationOptions, evaluate_scene
from .report import write_outputs
from .synthetic_experiment import run_synthetic_case

__all__ = ["EvaluationOptions", "evaluate_scene", "run_synthetic_case", "write_outputs"]
