"""The state of one render call (:class:`_Prepared`): what :mod:`mcdenoise.render.prepare` sets
up and :mod:`mcdenoise.render.motion` and :mod:`mcdenoise.render.trace` read."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class _Prepared:
    """Per-call state: integrator, sensor, motion bookkeeping."""

    integrator: Any
    sensor: Any
    width: int
    height: int
    has_lens: bool
    shutter_open: float
    shutter_time: float
    cam_start: np.ndarray | None = None
    cam_end: np.ndarray | None = None
    # param key (to_world or vertex_positions) -> (base value as float64 array, translation)
    motion: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    # vertex_positions key -> (its vertex_normals key, normals as loaded (float32, flat))
    normals: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)
    params: Any = None
    restore_camera: Any = None
