"""What to render: :class:`RenderSettings` and the per-sample channel list."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mcdenoise.errors import SceneError

__all__ = ["RenderSettings", "SAMPLE_CHANNELS", "REFERENCE_CHANNELS", "MAX_SIZE", "MAX_SPP"]

#: Per-sample channels the renderer can record, in the order it writes them.
SAMPLE_CHANNELS: tuple[str, ...] = (
    "radiance",
    "diffuse",
    "specular",
    "albedo",
    "normal",
    "depth",
    "albedo_diffuse",
    "normal_diffuse",
    "depth_diffuse",
    "roughness",
    "visibility",
    "lobes",
    "path_length",
    "subpixel",
    "lens",
    "time",
)
#: Channels of the reference image.
REFERENCE_CHANNELS: tuple[str, ...] = ("radiance", "diffuse", "specular", "albedo")

MAX_SIZE = 16384
MAX_SPP = 1 << 20


@dataclass
class RenderSettings:
    """How to render one image.

    Attributes:
        spp: samples per pixel of the per-sample (noisy) input.
        ref_spp: samples per pixel of the reference (0 = no reference).
        width, height: image size in pixels (overrides the scene's film).
        seed: base seed; the reference uses seeds derived from it, independent of the input's.
        max_depth: Mitsuba's convention (1 = emitters seen directly, 2 = direct lighting, ...);
            used by input and reference alike.
        channels: per-sample channels to record (None = all of SAMPLE_CHANNELS; ``radiance`` is
            always recorded).
        rr_depth: depth at which Russian roulette starts (Mitsuba's default 5).
        object_motion: shape id -> world translation over the shutter (object motion blur).
        camera_to_world_end: 4x4 camera-to-world at shutter close (camera motion blur).
        chunk_samples: samples traced per kernel launch (bounds memory, ~200 bytes per sample).
        ref_time_slices: most time slices of the reference when objects move (each slice is a
            scene update and a kernel launch, ~30-90 ms on 2 cores; the procedural dataset
            lowers it to what the on-screen motion needs).
    """

    spp: int = 8
    ref_spp: int = 4096
    width: int = 256
    height: int = 256
    seed: int = 0
    max_depth: int = 6
    channels: tuple[str, ...] | None = None
    rr_depth: int = 5
    object_motion: dict[str, tuple[float, float, float]] | None = None
    camera_to_world_end: Any = None
    chunk_samples: int = 1 << 21
    ref_time_slices: int = 256

    def check(self) -> None:
        """Raise SceneError on absurd values."""
        for name, v, lo, hi in (
            ("width", self.width, 1, MAX_SIZE),
            ("height", self.height, 1, MAX_SIZE),
            ("spp", self.spp, 1, MAX_SPP),
            ("ref_spp", self.ref_spp, 0, MAX_SPP),
            ("max_depth", self.max_depth, 1, 1024),
            ("chunk_samples", self.chunk_samples, 1, 1 << 31),
            ("ref_time_slices", self.ref_time_slices, 1, 1 << 20),
        ):
            if not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise SceneError(f"render settings: {name}={v!r} is out of range [{lo}, {hi}]")
        if self.channels is not None:
            bad = [c for c in self.channels if c not in SAMPLE_CHANNELS and c != "position"]
            if bad:
                raise SceneError(f"render settings: unknown per-sample channels {bad}; known: {list(SAMPLE_CHANNELS)}")

    def sample_channels(self) -> tuple[str, ...]:
        if self.channels is None:
            return SAMPLE_CHANNELS
        want = set(self.channels) | {"radiance"}
        return tuple(c for c in SAMPLE_CHANNELS if c in want)
