"""Open Image Denoise 2.5.1 as a method the denoise path can pick (``--model oidn``).

Not a registered model (no weights, no gradients, not tileable: OIDN tiles by itself): an object
that :func:`mcdenoise.infer.run.denoise_inputs` recognises and runs on the whole image, with the
albedo and normal guides when the input has them.
"""

from __future__ import annotations

import torch

from mcdenoise.models.base import Denoiser

__all__ = ["OIDN_NAME", "OIDNMethod"]

OIDN_NAME = "oidn"


class OIDNMethod(Denoiser):
    """OIDN ``high`` on the colour, with albedo + normal guides when present."""

    input_kind = "pixels"

    def __init__(self) -> None:
        super().__init__(None)

    def required_channels(self) -> list[str]:
        return ["radiance"]

    def forward(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:  # pragma: no cover - not called
        raise RuntimeError("OIDNMethod runs through denoise_inputs on the whole image")
