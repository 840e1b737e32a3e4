"""Where does a layer model's residual noise come from: the samples its kernels filter, or kernels
that follow the noise? (campaign 36; evidence for the next base.)

Campaign 35 found the per-sample models' gap to OIDN on the third-party scenes to be variance (noise
left in the output), and that a second stage does not remove it. This probe splits the base's
variance by what its kernels are computed from. Each image's samples are cut into ``n`` disjoint
sets of ``--spp`` (as ``scripts/bias_variance_probe.py``); for set ``j`` the layer model
(``layer-medium``) is run in three ways:

- ``own``: as it is (its kernels read set ``j``, the samples they filter);
- ``cross``: the layer sums of set ``j`` (Eq. 2: the samples' radiance, weights and occupancy per
  layer) filtered with the kernels computed from set ``j + 1`` (its layer embeddings and context), so
  the kernels know nothing of the noise they filter, and are as noisy themselves as in ``own``;
- ``ctx_all``: the context U-Net reads every stored sample's mean embedding (16 spp), the rest set
  ``j``: a nearly noise-free guide for the kernels (not a method: it reads 4x the samples);
- ``ctx_box``, ``ctx_guided``: the context U-Net reads set ``j``'s mean embedding smoothed over 3x3
  pixels, plainly or weighted by how alike the pixels' mean albedo and normal are (5x5,
  :func:`guided_smooth`): what a 4-spp method could do in ``ctx_all``'s direction without training;
- ``ctx_pass1``: the context U-Net reads the mean embedding of set ``j``'s samples with their
  radiance replaced by the model's own output on set ``j`` (a second pass whose guide is the first
  pass's denoised image; samples the network never saw, which agree exactly);
- ``ctx_shift``: the same, but each sample keeps its deviation from the samples' mean (its radiance
  is the first pass's output plus that deviation), so the context still sees how noisy the samples
  are, about a clean mean.

Each mode's outputs over the ``n`` sets give the bias/variance split of relMSE (same estimator as
``bias_variance_probe.split``). Reading it: if ``cross`` has much less variance than ``own``, the
kernels follow the noise of the samples they filter (a kernel built on one draw of the noise keeps
part of it); if ``ctx_all`` has much less, the noise of the guide drives it; if neither, the kernels'
footprint is what leaves the noise.

    python scripts/kernel_noise_probe.py data/scene_inputs/*spp16_seed* --spp 4 --model layer-medium
"""
from __future__ import annotations

import argparse
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

import mcdenoise  # noqa: F401  (sets up the package's defaults)
from bias_variance_probe import SampleSet, parts, split_maps  # scripts/ is on the path when a script runs
from mcdenoise.eval.images import collect_images
from mcdenoise.eval.methods import Inputs, ModelMethod
from mcdenoise.models.consistency import consistency_clamp
from mcdenoise.models.emitters import as_reflectance, batch_emitter_mask, fill_emitters, pass_through
from mcdenoise.models.exposure import scale_batch, unscale
from mcdenoise.models.layer import LayerDenoiser, shifted_samples
from mcdenoise.models.weights import load_denoiser

MODES = ("own", "cross", "ctx_all", "ctx_box", "ctx_guided", "ctx_pass1", "ctx_shift")
#: Scale of the guide distance in :func:`guided_smooth` (albedo in [0, 1], unit normals): a pixel whose
#: albedo or normal differs by 0.1 weighs exp(-1/2) of an identical one. Set before any measurement.
GUIDE_SIGMA = 0.1


def box_smooth(x: torch.Tensor, r: int = 1) -> torch.Tensor:
    """``x`` (B, C, H, W) averaged over (2r+1)^2 pixels, edges replicated."""
    return F.avg_pool2d(F.pad(x, (r, r, r, r), mode="replicate"), 2 * r + 1, stride=1)


def guided_smooth(x: torch.Tensor, guide: torch.Tensor, r: int = 2, sigma: float = GUIDE_SIGMA) -> torch.Tensor:
    """``x`` (B, C, H, W) averaged over (2r+1)^2 pixels with weights ``exp(-|g_q - g_p|^2 / (2 sigma^2))``,
    ``guide`` (B, G, H, W); edges replicated. A constant ``x`` stays constant (weights normalised)."""
    k = 2 * r + 1
    b, c, h, w = x.shape
    xs = F.unfold(F.pad(x, (r, r, r, r), mode="replicate"), k).view(b, c, k * k, h, w)
    gs = F.unfold(F.pad(guide, (r, r, r, r), mode="replicate"), k).view(b, guide.shape[1], k * k, h, w)
    wt = torch.exp(-((gs - guide.unsqueeze(2)) ** 2).sum(dim=1, keepdim=True) / (2 * sigma * sigma))
    return (xs * wt).sum(dim=2) / wt.sum(dim=2)


def pixel_guide(batch: dict[str, torch.Tensor]) -> torch.Tensor:
    """(B, 6, H, W): the samples' mean reflectance (albedo, clamped to [0, 1]) and mean normal."""
    return torch.cat([as_reflectance(batch["albedo"].mean(dim=1)).clamp(0, 1), batch["normal"].mean(dim=1)], dim=1)


def _inner(model: LayerDenoiser, batch: dict[str, torch.Tensor], scale: torch.Tensor | None) -> dict[str, torch.Tensor]:
    """``batch`` as the model's ``_denoise`` sees it: lights filled from their neighbours, at ``scale``."""
    inner = dict(fill_emitters(batch, batch_emitter_mask(batch, model.config.channels)))
    return inner if scale is None else scale_batch(inner, scale)


def _embed(model: LayerDenoiser, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """``(embeddings (B, S, E, H, W), radiance (B, S, 3, H, W))`` of the per-sample reducer."""
    f, radiance = model.features(batch)
    e = model.reducer(f)
    return e, radiance.to(e.dtype)


def layer_output(model: LayerDenoiser, batch: dict[str, torch.Tensor], kernels_from: dict[str, torch.Tensor] | None = None,
                 context_from: dict[str, torch.Tensor] | None = None,
                 context_filter: Callable[[torch.Tensor], torch.Tensor] | None = None) -> torch.Tensor:
    """``(B, 3, H, W)``: ``model``'s forward on ``batch`` (per-sample tensors ``(B, S, C, H, W)``),
    except that the kernel logits are computed from ``kernels_from`` (another draw of the same
    image's samples; its own layer embeddings and context) and/or the context U-Net reads
    ``context_from``'s mean embedding, and/or that mean embedding (B, E, H, W) goes through
    ``context_filter`` first. With none of them it is ``model(batch)`` (tested). Every batch is
    taken at ``batch``'s exposure scale; lights and the consistency clamp follow ``batch``."""
    cfg = model.config
    if cfg.hierarchical:
        raise ValueError("kernel_noise_probe: a hierarchical layer model is not supported")
    s = model.exposure_of(batch)
    e, radiance = _embed(model, _inner(model, batch, s))
    mean = _embed(model, _inner(model, context_from, s))[0].mean(dim=1) if context_from is not None else e.mean(dim=1)
    ctx = model._unet(mean if context_filter is None else context_filter(mean))[0]
    l_rad, l_w, l_n, l_emb = model.partition(e, ctx, radiance)
    if kernels_from is not None:
        ek, rk = _embed(model, _inner(model, kernels_from, s))
        ctx_k = ctx if context_from is not None else model._unet(ek.mean(dim=1))[0]
        l_emb, ctx = model.partition(ek, ctx_k, rk)[3], ctx_k
    out = model._filter(model.kernel_gen(l_emb, ctx), l_rad, l_w, l_n)
    out = pass_through(unscale(out, s), batch["radiance"], batch_emitter_mask(batch, cfg.channels))
    return consistency_clamp(out, batch["radiance"], cfg.consistency, cfg.consistency_min_spp, cfg.consistency_box)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("roots", nargs="+", help="datasets (their --split images) or image folders")
    ap.add_argument("--model", default="layer-medium", help="a layer model (shipped name, run folder or file)")
    ap.add_argument("--split", default="val")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES), help="which modes run (own always does)")
    ap.add_argument("--per-image", action="store_true", help="also print each image's total per mode")
    args = ap.parse_args(argv)
    modes = ["own"] + [m for m in args.modes if m != "own"]
    model, info = load_denoiser(args.model)
    if not isinstance(model, LayerDenoiser):
        raise SystemExit(f"kernel_noise_probe: {args.model} is not a layer model")
    meth = ModelMethod(args.model, model.eval(), info, "cpu")
    images = [e.folder for e in collect_images(args.roots, split=args.split)[0]]
    per: dict[str, list[tuple[float, float, float]]] = {}
    for im in images:
        n = im.meta.spp // args.spp
        if n < 2 or im.samples is None:
            raise SystemExit(f"{im.path}: needs per-sample data with at least {2 * args.spp} samples")
        ref = im.read_reference(["radiance"])["radiance"]
        sets = [meth.prepare(Inputs(SampleSet(im, j * args.spp), args.spp)) for j in range(n)]
        whole = meth.prepare(Inputs(im, n * args.spp)) if "ctx_all" in modes else None
        outs: dict[str, list[np.ndarray]] = {m: [] for m in modes}
        with torch.inference_mode():
            for j, b in enumerate(sets):
                g = pixel_guide(b)
                kw = {"own": {}, "cross": {"kernels_from": sets[(j + 1) % n]}, "ctx_all": {"context_from": whole},
                      "ctx_box": {"context_filter": box_smooth},
                      "ctx_guided": {"context_filter": lambda m, g=g: guided_smooth(m, g)}}
                own = layer_output(model, b)
                if "ctx_pass1" in modes:
                    kw["ctx_pass1"] = {"context_from": {**b, "radiance": own.unsqueeze(1).expand_as(b["radiance"])}}
                if "ctx_shift" in modes:
                    kw["ctx_shift"] = {"context_from": {**b, "radiance": shifted_samples(b["radiance"], own)}}
                for mode in modes:
                    outs[mode].append((own if mode == "own" else layer_output(model, b, **kw[mode]))[0].float().numpy())
        for mode, ys in outs.items():
            per.setdefault(mode, []).append(parts(*split_maps(np.stack(ys), ref)))
        if args.per_image:
            print(f"{im.path}: " + "  ".join(f"{m} {per[m][-1][0]:.5f}" for m in modes), flush=True)
    print(f"{args.model}: {len(images)} images, {args.spp} spp, {n} disjoint sample sets each; mean over images")
    print(f"{'mode':10s} {'total':>9s} {'bias':>9s} {'variance':>9s} | variance / own's | total / own's, geo mean of images")
    own = np.array(per["own"])
    for mode in modes:
        v = np.array(per[mode])
        geo = float(np.exp(np.log(v[:, 0] / own[:, 0]).mean()))
        print(f"{mode:10s} {v[:, 0].mean():9.5f} {v[:, 1].mean():9.5f} {v[:, 2].mean():9.5f} | "
              f"{v[:, 2].mean() / own[:, 2].mean():15.3f} | {geo:6.3f}")


if __name__ == "__main__":
    main()
