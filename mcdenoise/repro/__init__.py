"""Reproductions of paper experiments (``mcdenoise repro <experiment>``).

* ``splat-vs-gather``: SBMC Fig. 4 toy experiment, :mod:`mcdenoise.repro.splat_vs_gather`.
"""

from __future__ import annotations

__all__ = ["EXPERIMENTS"]

#: experiment name -> one-line description.
EXPERIMENTS: dict[str, str] = {
    "splat-vs-gather": "SBMC Fig. 4: downsample a texture with outlier samples, gather vs splat networks of equal capacity",
}
