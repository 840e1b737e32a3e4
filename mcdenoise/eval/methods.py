"""The denoisers ``mcdenoise eval`` compares, behind one two-step interface.

Each method splits its work into ``prepare`` (read and convert inputs: not timed) and ``run``
(the denoise call itself: timed), so the reported time per megapixel is the denoiser's alone.
Every method sees the inputs of the same ``k`` samples of an image through :class:`Inputs`,
which reads them once (:func:`mcdenoise.data.tensors.input_arrays`) and shares them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from mcdenoise.data.format import ImageFolder
from mcdenoise.data.tensors import input_arrays
from mcdenoise.eval.classic import NLMeansParams, feature_nlmeans
from mcdenoise.models.symmetry import self_ensemble

__all__ = ["Inputs", "Method", "NoisyMethod", "OIDNMethod", "ClassicMethod", "ModelMethod", "GUIDES"]

#: Per-pixel buffers the non-learned methods read: radiance, its variance, first-hit guides.
GUIDES = ("radiance", "radiance_variance", "albedo", "normal")


class Inputs:
    """The first ``k`` samples of one image, read lazily and shared by every method.

    ``guides`` holds (C, H, W) float32 means of :data:`GUIDES` (``albedo``/``normal`` only when
    the image stores them); :meth:`model_inputs` the arrays a model reads.
    """

    def __init__(self, folder: ImageFolder, k: int) -> None:
        self.folder, self.k = folder, k
        have = set(folder.meta.channels)
        names = [c for c in GUIDES if c.removesuffix("_variance") in have]
        if folder.samples is None:  # pixel-only: what noisy.exr holds (a converted Cycles file has no variance)
            held = set(folder.read_noisy())
            names = [c for c in names if c in held]
        self.guides: dict[str, np.ndarray] = input_arrays(folder, names, "pixels", spp=k)
        self._cache: dict[tuple[str, tuple[str, ...]], dict[str, np.ndarray]] = {}

    @property
    def radiance(self) -> np.ndarray:
        """(3, H, W) noisy radiance: the mean of the ``k`` samples."""
        return self.guides["radiance"]

    def model_inputs(self, channels: Sequence[str], input_kind: str) -> dict[str, np.ndarray]:
        key = (input_kind, tuple(channels))
        if key not in self._cache:
            self._cache[key] = input_arrays(self.folder, channels, input_kind, spp=self.k)
        return self._cache[key]


class Method:
    """One denoiser. ``name`` labels it in every table; ``info`` goes into results.json."""

    kind = ""

    def __init__(self, name: str) -> None:
        self.name = name

    @property
    def info(self) -> dict[str, Any]:
        return {"name": self.name, "kind": self.kind}

    @property
    def timed(self) -> bool:
        """False for the noisy input (nothing runs)."""
        return True

    def prepare(self, x: Inputs) -> Any:
        """Everything the denoise call needs, converted (not timed)."""
        return x

    def run(self, prepared: Any) -> np.ndarray:
        """The denoise call (timed): returns (3, H, W) linear radiance."""
        raise NotImplementedError


class NoisyMethod(Method):
    """The input itself: the mean of the first ``k`` samples."""

    kind = "noisy"

    def __init__(self) -> None:
        super().__init__("noisy")

    @property
    def timed(self) -> bool:
        return False

    def run(self, prepared: Inputs) -> np.ndarray:
        return prepared.radiance


class OIDNMethod(Method):
    """Open Image Denoise 2.5.1 (``pyoidn``), HDR, with the albedo and normal guides when stored;
    ``threads``: the CPU device's thread count (default every core). A quality ending in ``-pf``
    (``high-pf``) first denoises the guides with OIDN ``fast`` and passes them as clean: OIDN's
    documented best mode for noisy guides, at about twice the time."""

    kind = "oidn"

    def __init__(self, quality: str, threads: int | None = None) -> None:
        super().__init__(f"oidn-{quality}")
        from mcdenoise.eval.oidn import parse_quality

        self.quality, self.prefilter = parse_quality(quality)
        self.threads = threads
        self._used: int | None = None

    @property
    def info(self) -> dict[str, Any]:
        from mcdenoise.eval.oidn import device_threads, version

        if self._used is None:
            self._used = device_threads(self.threads)  # what the device reports, not what was asked
        return {**super().info, "quality": self.quality, "hdr": True, "guides": ["albedo", "normal"], "oidn": version(),
                "threads": self._used, **({"prefilter": self.prefilter} if self.prefilter else {})}

    def prepare(self, x: Inputs) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        g = x.guides
        albedo = g.get("albedo")
        return g["radiance"], albedo, g.get("normal") if albedo is not None else None

    def run(self, prepared: tuple[np.ndarray, np.ndarray | None, np.ndarray | None]) -> np.ndarray:
        from mcdenoise.eval.oidn import oidn_denoise

        color, albedo, normal = prepared
        return oidn_denoise(color, albedo, normal, hdr=True, quality=self.quality, threads=self.threads,
                            prefilter=self.prefilter)


class ClassicMethod(Method):
    """Feature-guided NL-means (:mod:`mcdenoise.eval.classic`), on the evaluation's torch device."""

    kind = "classic"

    def __init__(self, params: NLMeansParams | None = None, device: torch.device | str = "cpu") -> None:
        super().__init__("nlmeans")
        self.params = params or NLMeansParams()
        self.device = torch.device(device)

    @property
    def info(self) -> dict[str, Any]:
        return {**super().info, "method": "feature-guided NL-means (Rousselle et al. 2012 + albedo/normal weights)",
                "params": self.params.to_json()}

    def prepare(self, x: Inputs) -> dict[str, torch.Tensor | None]:
        g = {k: torch.from_numpy(np.ascontiguousarray(v)).to(self.device) for k, v in x.guides.items()}
        # One sample gives no variance estimate (pixel_stats returns zeros); the filter then
        # falls back to its own (see mcdenoise/eval/classic.py).
        return {"color": g["radiance"], "variance": g.get("radiance_variance") if x.k > 1 else None,
                "albedo": g.get("albedo"), "normal": g.get("normal")}

    def run(self, prepared: dict[str, torch.Tensor | None]) -> np.ndarray:
        with torch.inference_mode():
            out = feature_nlmeans(prepared["color"], variance=prepared["variance"], albedo=prepared["albedo"],  # type: ignore[arg-type]
                                  normal=prepared["normal"], params=self.params)
            return _to_numpy(out)


def _to_numpy(t: torch.Tensor) -> np.ndarray:
    """A result back on the CPU; the copy waits for CUDA work, so the timing includes it."""
    return t.detach().float().cpu().numpy()


class ModelMethod(Method):
    """A trained denoiser from :func:`mcdenoise.models.weights.load_denoiser`.

    Sample models get the ``k`` samples ``(1, k, C, H, W)`` and the scene features; pixel models
    the means and variances of those ``k`` samples ``(1, C, H, W)``.
    """

    kind = "model"

    def __init__(self, name: str, model: torch.nn.Module, load_info: dict[str, Any], device: torch.device | str,
                 precision: str = "float32", self_ensemble: bool = False) -> None:
        from mcdenoise.models.inference import prepare_inference

        super().__init__(name)
        #: Run in the 8 orientations and keep the per-pixel median (mcdenoise.models.symmetry); timed as one call.
        self.self_ensemble = self_ensemble
        self.parameters = sum(p.numel() for p in model.parameters())  # the trained form's, before folding
        # The inference form that bench times and denoise runs (WSKP's RepVGG blocks folded).
        self.model = prepare_inference(model, fast=True, precision=precision)
        self.load_info = load_info
        self.device = torch.device(device)

    @property
    def info(self) -> dict[str, Any]:
        params = self.parameters
        # load_info's "name" is the registered model; here "name" is this method's table label.
        loaded = {k: v for k, v in self.load_info.items() if k not in ("name", "label")}
        return {**super().info, "model": self.load_info.get("name"), "input_kind": self.model.input_kind,
                "parameters": params, **loaded, "self_ensemble": self.self_ensemble}

    def prepare(self, x: Inputs) -> dict[str, torch.Tensor]:
        m = self.model
        arrays = x.model_inputs(m.required_channels(), m.input_kind)
        batch = {k: torch.from_numpy(np.ascontiguousarray(v))[None].to(self.device) for k, v in arrays.items()}
        if m.input_kind == "samples":
            batch["scene_features"] = torch.from_numpy(x.folder.meta.scene_feature_vector())[None].to(self.device)
        # A pixel model's consistency clamp reads the same k samples' statistics (denoise's rule).
        self._stats = (x.guides["radiance"], x.guides.get("radiance_variance"), x.k)
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)  # the copies are not the model's time
        return batch

    def run(self, prepared: dict[str, torch.Tensor]) -> np.ndarray:
        with torch.inference_mode():
            if self.self_ensemble:
                out = self_ensemble(lambda b: _to_numpy(self.model(b)[0]), prepared)
            else:
                out = _to_numpy(self.model(prepared)[0])
        return self.model.pixel_consistency(out, *self._stats)
