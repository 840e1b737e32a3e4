"""Evaluation: metrics, the OIDN and NL-means baselines, and ``mcdenoise eval``'s report.

``mcdenoise.eval.evaluate(models=..., data=..., out=...)`` runs what ``mcdenoise eval`` runs
(see :mod:`mcdenoise.eval.runner` and docs/EVAL.md).
"""

from mcdenoise.eval.runner import EvalError, evaluate

__all__ = ["evaluate", "EvalError"]
