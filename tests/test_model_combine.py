"""The combiner (issue 20): its guarantees, the derived ``oidn`` channel and its cache."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from mcdenoise.models import build_model, synthetic_batch
from mcdenoise.models.combine import apply_weights

pytest.importorskip("pyoidn")


def _randomised(seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    model = build_model("combine", "small").eval()
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0, 0.5)  # far from the identity start: weights spread over every tap
    return model


def test_output_stays_within_the_candidates_neighbourhood() -> None:
    """Catches weights that are not a partition of unity (negative, or not summing to 1): the
    output would leave the range of the candidate values it combines, i.e. invent radiance."""
    model = _randomised()
    batch = synthetic_batch(model, height=23, width=29, generator=torch.Generator().manual_seed(3))
    batch["radiance"] = batch["radiance"] * torch.exp(torch.randn_like(batch["radiance"]) * 3)  # HDR, fireflies
    with torch.no_grad():
        out = model(batch)
    both = torch.stack([batch["oidn"], batch["radiance"]])
    hi = F.max_pool2d(F.pad(both.amax(0), (1, 1, 1, 1), mode="replicate"), 3, 1)
    lo = -F.max_pool2d(F.pad(-both.amin(0), (1, 1, 1, 1), mode="replicate"), 3, 1)
    assert (out <= hi * (1 + 1e-5) + 1e-6).all() and (out >= lo * (1 - 1e-5) - 1e-6).all()


def test_constant_candidates_give_the_constant() -> None:
    """Catches zero-padded taps at the border (a dark frame) or unnormalised weights."""
    model = _randomised(1)
    batch = synthetic_batch(model, height=17, width=19)
    batch["oidn"] = torch.full_like(batch["oidn"], 0.7)
    batch["radiance"] = torch.full_like(batch["radiance"], 0.7)
    with torch.no_grad():
        out = model(batch)
    torch.testing.assert_close(out, torch.full_like(out, 0.7), rtol=1e-5, atol=1e-6)


def test_a_fresh_combiner_returns_oidn() -> None:
    """Catches an initialisation that starts training from a blur of OIDN and the noise (the
    combiner must start as OIDN and move away only where the data says so)."""
    torch.manual_seed(0)
    model = build_model("combine", "small").eval()
    batch = synthetic_batch(model, height=16, width=16)
    with torch.no_grad():
        out = model(batch)
    assert float(((out - batch["oidn"]).abs() / (batch["oidn"].abs() + 1e-2)).mean()) < 0.1


def test_apply_weights_matches_a_loop_in_float64() -> None:
    """Catches a tap order that does not match the weights (unfold order vs (dy, dx))."""
    g = torch.Generator().manual_seed(0)
    c = [torch.rand(1, 3, 6, 7, generator=g, dtype=torch.float64) for _ in range(2)]
    w = torch.softmax(torch.randn(1, 18, 6, 7, generator=g, dtype=torch.float64), dim=1)
    out = apply_weights(c, w, 3)
    ref = torch.zeros_like(out)
    for ci, img in enumerate(c):
        p = F.pad(img, (1, 1, 1, 1), mode="replicate")
        for t in range(9):
            dy, dx = divmod(t, 3)
            ref += w[:, ci * 9 + t : ci * 9 + t + 1] * p[..., dy : dy + 6, dx : dx + 7]
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)
    torch.autograd.gradcheck(lambda a, b, ww: apply_weights([a, b], ww, 3),
                             (c[0].requires_grad_(), c[1].requires_grad_(), w.clone().requires_grad_()))


def test_oidn_channel_is_cached_beside_the_dataset_and_matches_oidn(tmp_path: Path) -> None:
    """Catches a cached OIDN image for the wrong samples (the input uses the first k), a cache
    written outside the dataset's .cache, or one computed again on every read."""
    from train_tiny_data import make_tiny_dataset

    from mcdenoise.data.dataset import Dataset
    from mcdenoise.data.oidn_input import oidn_for
    from mcdenoise.data.tensors import input_arrays
    from mcdenoise.eval.oidn import oidn_denoise, version

    root = make_tiny_dataset(tmp_path / "d")
    im = Dataset(root).images("train")[0]
    a = oidn_for(im, 3)
    px = input_arrays(im, ["radiance", "albedo", "normal"], "pixels", spp=3)
    np.testing.assert_array_equal(a, oidn_denoise(px["radiance"], px["albedo"], px["normal"]))
    [cached] = list((root / ".cache" / f"oidn-{version()}").rglob("high_spp3.npy"))
    stamp = cached.stat().st_mtime_ns
    np.testing.assert_array_equal(oidn_for(im, 3), a)
    assert cached.stat().st_mtime_ns == stamp
    assert not np.array_equal(oidn_for(im, 2), a)


def test_crops_for_the_combiner_use_the_first_samples(tmp_path: Path) -> None:
    """Catches random sample subsets for the input while OIDN's cached image used the first k:
    the two candidates would disagree on the noise, and the target would overlap the input."""
    from train_tiny_data import make_tiny_dataset

    from mcdenoise.data.dataset import Dataset
    from mcdenoise.data.sampler import CropSampler

    root = make_tiny_dataset(tmp_path / "d")
    model = build_model("combine", "small")
    s = CropSampler(Dataset(root).images("train"), crop=8, channels=model.required_channels(), kind="pixels",
                    spp_range=(2, 5), target="noisy", seed=0)
    for i in range(6):
        c = s[i]
        n = len(c.samples)
        assert c.samples == list(range(n)) and c.target_samples == list(range(n, 8))
        assert c.inputs["oidn"].shape == (3, 8, 8)


def _randomised_ens(seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    model = build_model("combine", "ens").eval()
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0, 0.5)
    return model


def test_the_prefiltered_combiner_stays_within_its_three_candidates() -> None:
    """Catches the third candidate (``oidn_pf``) left out of the weights or the normalisation: the
    output would leave the per-pixel range of OIDN, prefiltered OIDN and the clamped noisy mean."""
    model = _randomised_ens()
    assert model.required_channels()[:3] == ["oidn", "oidn_pf", "radiance"]
    batch = synthetic_batch(model, height=21, width=18, generator=torch.Generator().manual_seed(4))
    batch["oidn_pf"] = batch["oidn_pf"] * 5  # far from the others: its weight shows
    with torch.no_grad():
        out, w = model(batch), model.weights(batch)
        cands = torch.stack(model.candidates(batch))
    assert w.shape[1] == 3 and torch.allclose(w.sum(1), torch.ones_like(w[:, 0]))
    assert (out <= cands.amax(0) * (1 + 1e-5) + 1e-6).all() and (out >= cands.amin(0) * (1 - 1e-5) - 1e-6).all()
    assert float(w[:, 1].mean()) > 1e-3  # the prefiltered candidate is really used
    const = {k: (torch.full_like(v, 0.3) if k in ("oidn", "oidn_pf", "radiance") else v) for k, v in batch.items()}
    with torch.no_grad():
        torch.testing.assert_close(model(const), torch.full_like(out, 0.3), rtol=1e-5, atol=1e-6)


def test_every_parameter_of_the_prefiltered_combiner_gets_a_gradient() -> None:
    """Catches features of the third candidate that are computed but never reach the network."""
    model = build_model("combine", "ens").train()
    batch = synthetic_batch(model, height=16, width=16, generator=torch.Generator().manual_seed(1))
    for k in ("oidn", "oidn_pf", "radiance"):
        batch[k] = batch[k].abs() + 0.1
    model(batch).square().mean().backward()
    assert all(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in model.parameters())
    # the prefiltered features move the weights: the same batch with another oidn_pf gives other weights
    with torch.no_grad():
        w1 = model.weights(batch)
        w2 = model.weights({**batch, "oidn_pf": batch["oidn_pf"] * 3})
    assert not torch.allclose(w1, w2)


def test_prefiltered_oidn_channel_is_cached_apart_from_the_plain_one(tmp_path: Path) -> None:
    """Catches the two derived OIDN channels sharing one cache file (a combiner would get the same
    image twice) or ``oidn_pf`` computed without prefiltering."""
    from train_tiny_data import make_tiny_dataset

    from mcdenoise.data.dataset import Dataset
    from mcdenoise.data.oidn_input import oidn_for
    from mcdenoise.data.tensors import input_arrays
    from mcdenoise.eval.oidn import oidn_denoise, version

    root = make_tiny_dataset(tmp_path / "d")
    im = Dataset(root).images("train")[0]
    plain, pf = oidn_for(im, 3), oidn_for(im, 3, channel="oidn_pf")
    px = input_arrays(im, ["radiance", "albedo", "normal"], "pixels", spp=3)
    np.testing.assert_array_equal(pf, oidn_denoise(px["radiance"], px["albedo"], px["normal"], prefilter="fast"))
    assert not np.array_equal(plain, pf)
    cache = root / ".cache" / f"oidn-{version()}"
    assert len(list(cache.rglob("high_spp3.npy"))) == 1 and len(list(cache.rglob("high_pf-fast_spp3.npy"))) == 1
    got = input_arrays(im, ["radiance", "oidn", "oidn_pf"], "pixels", spp=3)
    np.testing.assert_array_equal(got["oidn_pf"], pf)
    np.testing.assert_array_equal(got["oidn"], plain)


def test_a_halo_over_a_missed_pixel_gives_way_to_the_noisy_mean() -> None:
    """Catches the rich-world failure: OIDN spreads a bright bulb over a dark sky whose samples all
    missed the scene (albedo and normal 0); the combination there must fall back to the noisy
    mean, and nowhere else (a pixel with a surface, or a miss near its noisy mean, is untouched)."""
    torch.manual_seed(0)
    model = build_model("combine", "ens").eval()
    batch = synthetic_batch(model, height=8, width=8)
    for k in ("oidn", "oidn_pf"):
        batch[k] = torch.full_like(batch[k], 2.0)
    batch["radiance"] = torch.full_like(batch["radiance"], 0.007)
    batch["albedo"][..., :4] = 0
    batch["normal"][..., :4] = 0  # left half: every sample missed
    batch["radiance"][..., 0, 4:] = 3.0  # one row of the surface half: noisy near OIDN
    with torch.no_grad():
        out = model(batch)
        model.config.miss_halo = 0
        off = model(batch)
    torch.testing.assert_close(out[..., :4], batch["radiance"][..., :4])
    torch.testing.assert_close(out[..., 4:], off[..., 4:])
    assert float(off[..., :4].min()) > 1.0  # without the rule the halo stays


@pytest.mark.parametrize("preset,kernel", [("ens", 1), ("small_k3", 3)])
def test_shrink_blends_the_learned_combination_toward_oidn(preset: str, kernel: int) -> None:
    """``shrink`` a: catches the share moved to a tap other than OIDN's centre (with 3x3 taps the
    centre is tap 4, not 0), weights that no longer sum to 1, and any output other than exactly
    ``OIDN + a * (learned - OIDN)`` (float64, where the blend is exact to rounding)."""
    from dataclasses import replace

    from mcdenoise.models.combine import Combine

    torch.manual_seed(5)
    full = build_model("combine", preset).double().eval()
    with torch.no_grad():
        for p in full.parameters():
            p.normal_(0, 0.5)
    half = Combine(replace(full.config, shrink=0.5)).double().eval()
    half.load_state_dict(full.state_dict())
    assert full.config.kernel == kernel
    batch = synthetic_batch(full, height=13, width=15, dtype=torch.float64, generator=torch.Generator().manual_seed(6))
    with torch.no_grad():
        w = half.weights(batch)
        a, b = half(batch), full(batch)
    torch.testing.assert_close(w.sum(1), torch.ones_like(w[:, 0]))
    oidn = batch["oidn"]
    halo = (batch["albedo"].abs().sum(1, keepdim=True) == 0) & (batch["normal"].abs().sum(1, keepdim=True) == 0)
    want = torch.where(halo, a, oidn + 0.5 * (b - oidn))  # the miss-halo rule acts after the blend
    torch.testing.assert_close(a, want, rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="shrink"):
        Combine(replace(full.config, shrink=0.0))


def test_noisy_clamp_min_bounds_a_spike_that_plain_oidn_keeps() -> None:
    """Catches the noisy candidate reaching the output through plain OIDN's clamp where only plain
    OIDN kept a spike (a sun in a chrome sphere that one sample of four hit, Blender dof render
    at 4 spp: 14.8x OIDN high's relMSE with the plain clamp, 0.19x with ``min``): with
    ``noisy_clamp_ref="min"`` no output exceeds the largest of the two OIDN candidates and 8x the
    3x3 maximum of their per-pixel minimum; where prefiltered OIDN is the brighter one everywhere,
    ``min`` is exactly the plain clamp."""
    from mcdenoise.models.weights import model_from_config

    base = _randomised_ens()
    cfg = {**base.config.__dict__, "noisy_clamp_ref": "min"}
    model = model_from_config("combine", "ens", cfg)
    model.load_state_dict(base.state_dict())
    model.eval()
    batch = synthetic_batch(model, height=16, width=16, generator=torch.Generator().manual_seed(6))
    batch = {k: v.clone() for k, v in batch.items()}
    batch["radiance"][..., 8, 8] = 4000.0
    batch["oidn"][..., 8, 8] = 200.0
    batch["oidn_pf"] = batch["oidn"].clamp_max(2.0)
    with torch.no_grad():
        out_min, out_plain = model(batch), base(batch)
        cands = torch.stack(model.candidates(batch))
    low = torch.minimum(batch["oidn"], batch["oidn_pf"]).clamp_min(0)
    bound = torch.maximum(torch.maximum(batch["oidn"], batch["oidn_pf"]),
                          8 * F.max_pool2d(F.pad(low, (1, 1, 1, 1), mode="replicate"), 3, stride=1))
    assert (cands[2] <= 8 * F.max_pool2d(F.pad(low, (1, 1, 1, 1), mode="replicate"), 3, stride=1) + 1e-4).all()
    assert (out_min <= bound * (1 + 1e-5) + 2e-4).all()  # the clamp adds EPS (1e-4)
    spike_min = float(cands[2][..., 8, 8].max())
    with torch.no_grad():
        spike_plain = float(torch.stack(base.candidates(batch))[2][..., 8, 8].max())
    assert spike_min <= 8 * 2.0 + 1e-3 < 1500 < spike_plain  # 8x plain OIDN's 200 reaches the output's choice
    assert out_plain.shape == out_min.shape
    batch["oidn_pf"] = batch["oidn"] * 1.5 + 0.1  # prefiltered brighter everywhere: min is plain OIDN
    with torch.no_grad():
        torch.testing.assert_close(model(batch), base(batch), rtol=0, atol=0)


def _with_kernel_candidate(seed: int = 0) -> torch.nn.Module:
    """An ``ens_kpcn`` combiner with its weight network randomised far from the identity start."""
    torch.manual_seed(seed)
    model = build_model("combine", "ens_kpcn")
    with torch.no_grad():
        for p in model.net.parameters():
            p.normal_(0, 0.5)
    return model.eval()


def test_the_kernel_candidate_combiner_stays_within_its_four_candidates() -> None:
    """Catches a kernel candidate outside the partition of unity (its weight not normalised with
    the others, or the candidate list and the weight channels out of step): the output would leave
    the range of OIDN, prefiltered OIDN, the clamped noisy mean and the kernel model's output."""
    model = _with_kernel_candidate()
    batch = synthetic_batch(model, height=21, width=27, generator=torch.Generator().manual_seed(5))
    batch["radiance"] = batch["radiance"] * torch.exp(torch.randn_like(batch["radiance"]) * 3)
    with torch.no_grad():
        kernel = model.kernel_output(batch)
        out = model(batch)
        cands = torch.stack(model.candidates(batch, kernel))
    assert cands.shape[0] == 4 and model.net.final.weight.shape[0] == 4
    with torch.no_grad():
        weights = model.weights(batch, kernel)
    torch.testing.assert_close(weights.sum(1), torch.ones_like(weights[:, 0]))
    assert float(weights[:, 3].mean()) > 1e-3  # the randomised network does use the kernel candidate
    assert (out <= cands.amax(0) * (1 + 1e-5) + 1e-6).all() and (out >= cands.amin(0) * (1 - 1e-5) - 1e-6).all()


def test_the_kernel_model_stays_frozen_while_the_weight_network_trains() -> None:
    """Catches combiner training moving the kernel model it was given (its weights are a shipped
    model's; a step on the combiner's loss must leave them bit-identical) and a kernel model left in
    training mode by ``model.train()``."""
    model = _with_kernel_candidate(1).train()
    assert not model.kernel_model.training
    before = {k: v.clone() for k, v in model.kernel_model.state_dict().items()}
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=1e-2)
    batch = synthetic_batch(model, height=16, width=16, generator=torch.Generator().manual_seed(2))
    loss = model(batch).square().mean()
    loss.backward()
    assert all(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in model.net.parameters())
    opt.step()
    for k, v in model.kernel_model.state_dict().items():
        assert torch.equal(v, before[k]), k


def test_a_kernel_candidate_combiner_rebuilds_from_its_file_alone(tmp_path: Path) -> None:
    """Catches a combiner whose file does not carry its kernel model's configuration (it would
    rebuild the preset's kernel model, which the saved tensors may not fit, or fit with other
    rules), and an autoexposure that tiled inference cannot see through the combiner."""
    import json

    from safetensors.torch import save_file

    from mcdenoise.models.weights import load_denoiser, model_from_config

    cfg = {"kernel_candidate": "kpcn:pixel", "kernel_candidate_config": {"autoexposure": 0.18, "kernel_size": 7}}
    model = model_from_config("combine", "ens_kpcn", cfg)
    assert model.kernel_model.config.kernel_size == 7 and model.autoexposure == 0.18
    path = tmp_path / "c.safetensors"
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(path),
              metadata={"model": "combine", "preset": "ens_kpcn", "model_config": json.dumps(cfg)})
    back, _ = load_denoiser(path)
    assert back.kernel_model.config.kernel_size == 7 and back.autoexposure == 0.18
    for k, v in model.state_dict().items():
        assert torch.equal(v, back.state_dict()[k]), k


def test_kernel_candidate_tiles_are_seam_free() -> None:
    """Catches tiled inference of a combiner whose kernel model has autoexposure measuring each tile's
    own scale (the combiner must expose its kernel model's key, so the tile driver measures the whole
    image once), and a receptive-field probe blind to the kernel model (its output computed without
    input gradients: the probe then plans tile margins for the weight network alone)."""
    from mcdenoise.infer.receptive import measure_receptive_field
    from mcdenoise.models.weights import model_from_config

    torch.manual_seed(4)
    model = model_from_config("combine", "ens_kpcn", {"kernel_candidate_config": {"autoexposure": 0.18}})
    with torch.no_grad():
        for p in model.net.parameters():
            p.normal_(0, 0.3)
    model = model.eval()
    from test_model_exposure import assert_tiles_match_whole

    assert_tiles_match_whole(model, 64, 72)
    # The kernel model reads 10 px around a pixel and the weight network reads its output: the two add.
    assert measure_receptive_field(model) > measure_receptive_field(build_model("combine", "ens"))


def test_kernel_clamp_bounds_a_spread_firefly_but_not_a_darker_candidate() -> None:
    """Catches the kernel candidate's clamp missing (a firefly the kernel model spread reaches the
    output at full strength) or cutting from below (the kernel model's darker value beside an OIDN
    halo, the reason it is a candidate, would be lost)."""
    from mcdenoise.models.weights import model_from_config

    model = model_from_config("combine", "ens_kpcn", {"kernel_clamp": 1.0}).double().eval()
    batch = synthetic_batch(model, height=12, width=12, generator=torch.Generator().manual_seed(1))
    batch = {k: v.double() for k, v in batch.items()}
    batch["oidn"] = torch.full_like(batch["oidn"], 2.0)
    batch["oidn_pf"] = torch.full_like(batch["oidn"], 1.0)
    batch["oidn_pf"][..., 6, 6] = 0.2  # a dark pixel beside the firefly: a neighbourhood would not bind
    kernel = torch.full_like(batch["oidn"], 0.5)
    kernel[..., 5, 5] = 40.0  # a spread firefly
    kernel[..., 6, 6] = 0.9
    cands = model.candidates(batch, kernel)
    assert cands[3][..., 5, 5].max() <= 1.0 + 1e-3  # the dimmer OIDN candidate at that pixel
    assert cands[3][..., 6, 6].max() <= 0.2 + 1e-3
    assert torch.equal(cands[3][..., 0, 0], kernel[..., 0, 0])  # darker than OIDN: untouched
    off = model_from_config("combine", "ens_kpcn", {}).double()
    assert float(off.candidates(batch, kernel)[3][..., 5, 5].max()) == 40.0


def _with_own_kernel(seed: int = 0, **fields: object) -> torch.nn.Module:
    from mcdenoise.models.weights import model_from_config

    torch.manual_seed(seed)
    model = model_from_config("combine", "own", dict(fields))
    with torch.no_grad():
        for p in model.net.parameters():
            p.normal_(0, 0.3)
    return model.eval()


def test_the_own_kernel_combiner_stays_within_its_candidates() -> None:
    """Catches the own kernel's candidate outside the partition of unity (its weight channel and
    its K*K logits out of step in the network's output, or the candidate list in another order
    than the weights): the output would leave the range of OIDN, the clamped noisy mean and the
    clamped own candidate."""
    model = _with_own_kernel()
    batch = synthetic_batch(model, height=21, width=27, generator=torch.Generator().manual_seed(5))
    batch["radiance"] = batch["radiance"] * torch.exp(torch.randn_like(batch["radiance"]) * 3)
    with torch.no_grad():
        weights, own = model.predict(batch)
        cands = torch.stack(model.candidates(batch, None, own))
        out = model(batch)
    assert cands.shape[0] == 3 and weights.shape[1] == 3
    torch.testing.assert_close(weights.sum(1), torch.ones_like(weights[:, 0]))
    assert float(weights[:, 2].mean()) > 1e-3  # the randomised network does use the own candidate
    assert (out <= cands.amax(0) * (1 + 1e-5) + 1e-6).all() and (out >= cands.amin(0) * (1 - 1e-5) - 1e-6).all()
    assert (cands[2] <= batch["oidn"].clamp_min(0) + 1e-4 + 1e-6).all()  # kernel_clamp 1: never above OIDN


def test_the_own_kernel_keeps_a_constant_image_and_filters_in_the_albedo_domain() -> None:
    """Catches a kernel that is not normalised (a constant irradiance would change), zero padding at
    the border (a dark frame), and a remodulation with the wrong albedo (a texture of constant
    irradiance would be blurred: the candidate must give radiance = albedo * irradiance back)."""
    model = _with_own_kernel(1, kernel_clamp=0.0)
    batch = synthetic_batch(model, height=17, width=19, generator=torch.Generator().manual_seed(2))
    albedo = torch.rand_like(batch["albedo"]) * 0.9 + 0.05  # a texture
    batch["albedo"] = albedo
    batch["radiance"] = 0.3 * (albedo + 0.00316)  # lit evenly: constant irradiance 0.3
    with torch.no_grad():
        _, own = model.predict(batch)
    torch.testing.assert_close(own, batch["radiance"], rtol=1e-5, atol=1e-6)


def test_the_own_kernel_banded_inference_matches_the_training_path() -> None:
    """Catches the inference path (row bands, logits in any layout) disagreeing with the
    differentiable one the network was trained through: masking, softmax or tap order."""
    model = _with_own_kernel(2, kernel_clamp=0.0).double()
    batch = {k: v.double() for k, v in synthetic_batch(model, height=19, width=23, generator=torch.Generator().manual_seed(4)).items()}
    with torch.no_grad():
        _, own_banded = model.predict(batch)
    with torch.enable_grad():
        _, own_grad = model.predict(batch)
    torch.testing.assert_close(own_banded, own_grad.detach(), rtol=1e-10, atol=1e-12)


def test_every_parameter_of_the_own_kernel_combiner_gets_a_gradient_from_each_loss() -> None:
    """Catches an own-kernel head cut off from training: no gradient through the image loss (its
    candidate not among the weighted ones) or through its own loss term (forward_aux not giving it)."""
    model = _with_own_kernel(3).train()
    batch = synthetic_batch(model, height=16, width=16, generator=torch.Generator().manual_seed(2))
    out = model.forward_aux(batch)
    assert set(out) == {"image", "own"} and model.aux_loss_weights()["own"] > 0
    out["own"].square().mean().backward()
    final = model.net.final.weight.grad
    assert final is not None and bool(final[3:].abs().sum() > 0)  # the K*K logits get the own loss
    model.zero_grad()
    model(batch).square().mean().backward()
    assert all(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in model.net.parameters())


def test_trainer_adds_the_own_kernel_loss() -> None:
    """Catches the trainer ignoring forward_aux (the own candidate would learn only where the
    combination already uses it) or weighting it other than the model says."""
    from mcdenoise.train.config import TrainConfig
    from mcdenoise.train.trainer import Trainer

    model = _with_own_kernel(4).train()
    batch = synthetic_batch(model, height=16, width=16, generator=torch.Generator().manual_seed(6))
    batch["target"] = torch.rand_like(batch["radiance"])
    cfg = TrainConfig(model="combine", preset="own", data="unused", loss="l1").resolved(model.input_kind)
    trainer = Trainer(model, cfg, torch.device("cpu"))
    with torch.no_grad():
        total = float(trainer.compute_loss(batch, 10**6))
        aux = model.forward_aux(batch)
    l1 = lambda a: float((a - batch["target"]).abs().mean())  # noqa: E731
    assert total == pytest.approx(l1(aux["image"]) + 0.5 * l1(aux["own"]), rel=1e-5)


def _emitter_batch(model: torch.nn.Module, seed: int = 7) -> dict[str, torch.Tensor]:
    """A batch in Cycles' convention: a few pixels whose albedo is a light's radiance (> 1)."""
    batch = synthetic_batch(model, height=19, width=23, generator=torch.Generator().manual_seed(seed))
    batch["albedo"] = batch["albedo"].clamp(0, 1)
    batch["albedo"][:, :, 5:7, 8:11] = 40.0
    batch["radiance"][:, :, 5:7, 8:11] = 40.0
    return batch


def test_the_emitter_feature_marks_exactly_the_pixels_with_albedo_above_one() -> None:
    """Catches an emitter channel built from the clamped albedo (all zeros: the network still could
    not tell a light from a white wall) or one that is non-zero on our own convention (albedo <= 1,
    0 on a miss), where it would change a trained combiner's output."""
    from mcdenoise.models.combine import combine_features

    model = build_model("combine", "ens")
    batch = _emitter_batch(model)
    feats = combine_features(batch, prefiltered=True, emitter=True)
    mask = feats[:, -1]
    assert torch.equal(mask.bool(), (batch["albedo"].amax(1) > 1))
    batch["albedo"] = batch["albedo"].clamp(0, 1)
    assert float(combine_features(batch, prefiltered=True, emitter=True)[:, -1].abs().sum()) == 0.0


def test_zero_new_inputs_starts_the_emitter_combiner_where_the_old_one_was(tmp_path: Path) -> None:
    """Catches `reconfigure_weights.py --zero-new-inputs` padding the first convolution anywhere but
    where the feature sits (the last channel): the reconfigured combiner would not compute what the
    source did, so a fine-tune would start from damaged weights. Also that training then gives the
    new channel a gradient (it would otherwise stay zero for ever)."""
    import json
    import subprocess
    import sys

    from safetensors.torch import save_file

    from mcdenoise.models.weights import load_denoiser

    src = _with_kernel_candidate(3)
    cfg = json.loads(json.dumps({k: v for k, v in vars(src.config).items()}))
    path, dst = tmp_path / "src.safetensors", tmp_path / "dst.safetensors"
    save_file({k: v.contiguous() for k, v in src.state_dict().items()}, str(path),
              metadata={"model": "combine", "preset": "ens_kpcn", "model_config": json.dumps(cfg)})
    script = Path(__file__).resolve().parent.parent / "scripts" / "reconfigure_weights.py"
    subprocess.run([sys.executable, str(script), str(path), str(dst), "--zero-new-inputs", "--set", "emitter_feature=true"],
                   check=True, capture_output=True)
    new, _ = load_denoiser(dst)
    def first(m: torch.nn.Module) -> torch.nn.Parameter:
        return next(p for p in m.net.parameters() if p.dim() == 4)

    assert new.config.emitter_feature and first(new).shape[1] == first(src).shape[1] + 1
    batch = {k: v.double() for k, v in _emitter_batch(src).items()}
    with torch.no_grad():  # float64: a zero channel only reorders the convolution's sums
        torch.testing.assert_close(new.double().eval()(batch), src.double()(batch))
    new.train()
    new(batch).square().mean().backward()
    assert float(first(new).grad[:, -1].abs().sum()) > 0
