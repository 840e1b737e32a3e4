"""Seeds derived from integers (never from the clock): the two derivations the datasets rely on.

They differ on purpose and must stay as they are: every dataset rendered so far was made with both
(changing either changes every image of a re-render), so each keeps its behaviour under a name
that says what it seeds.

* :func:`derive_seed` ``(*ints)``: 31-bit seeds for *drawing*: the scene of dataset image ``i``
  (``derive_seed(dataset_seed, i)``), re-drawn scenes, extra views, previews, the exposure target
  and the render seed a dataset hands to the renderer. Recorded in each image's ``meta.json``.
* :func:`stream_seed` ``(seed, *keys)``: 32-bit seeds of the renderer's own random streams from one
  render seed: bands of a streamed render, per-sample passes, reference passes, time slices. Its
  keys are mixed with a fixed tag, so a stream never repeats the stream of the seed it came from.
"""

from __future__ import annotations

import numpy as np

__all__ = ["derive_seed", "stream_seed"]


def derive_seed(*ints: int) -> int:
    """A 31-bit seed derived from integers, e.g. ``(dataset_seed, image_index)`` (no clock)."""
    ss = np.random.SeedSequence([int(i) & 0xFFFFFFFFFFFFFFFF for i in ints])
    return int(ss.generate_state(1, np.uint32)[0] >> 1)


def stream_seed(seed: int, *keys: int) -> int:
    """A 32-bit seed derived from ``seed`` and ``keys`` (independent streams per key tuple)."""
    ss = np.random.SeedSequence([int(seed) & 0xFFFFFFFF, 0x6D63646E, *[int(k) & 0xFFFFFFFF for k in keys]])
    return int(ss.generate_state(1, dtype=np.uint32)[0])
