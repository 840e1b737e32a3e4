"""Reproductions of paper experiments (``mcdenoise repro <experiment>``).

* ``splat-vs-gather``: SBMC Fig. 4 toy experiment, :mod:`mcdenoise.repro.splat_vs_gather`.
* ``kpcn-vs-dpcn``, ``sbmc-table2``, ``layer-table2``, ``wskp-fig9``: the papers' claims trained
  on our data with the training engine, one module each; what they share (data cache, runs,
  result JSON) is in :mod:`mcdenoise.repro.common`, the plot and Markdown in
  :mod:`mcdenoise.repro.report`.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = ["EXPERIMENTS", "TRAINED", "load_experiment"]

#: experiment name -> one-line description.
EXPERIMENTS: dict[str, str] = {
    "splat-vs-gather": "SBMC Fig. 4: downsample a texture with outlier samples, gather vs splat networks of equal capacity",
    "kpcn-vs-dpcn": "Bako et al. 2017 Fig. 9: KPCN converges faster than DPCN (validation L1 against steps)",
    "sbmc-table2": "Gharbi et al. 2019 Table 2: SBMC vs Gather vs PixelGather vs PixelSplat at equal parameters",
    "layer-table2": "Munkberg & Hasselgren 2020 Tables 1-2: 1, 2, 4 layers; alpha vs weighted-sum compositing",
    "wskp-fig9": "Fan et al. 2021 Fig. 9: kernel fusion vs each single kernel size",
}

#: The experiments trained with the training engine: name -> module under mcdenoise.repro.
TRAINED: dict[str, str] = {
    "kpcn-vs-dpcn": "kpcn_vs_dpcn",
    "sbmc-table2": "sbmc_table2",
    "layer-table2": "layer_table2",
    "wskp-fig9": "wskp_fig9",
}


def load_experiment(name: str) -> Any:
    """The :class:`~mcdenoise.repro.common.Experiment` of a trained experiment (imports torch)."""
    if name not in TRAINED:
        raise KeyError(f"unknown experiment {name!r}; trained experiments: {', '.join(TRAINED)}")
    return importlib.import_module(f"mcdenoise.repro.{TRAINED[name]}").EXPERIMENT
