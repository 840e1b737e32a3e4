"""Training engine parts without a full run: losses, schedule, the non-finite guard, checkpoints,
metrics.csv recovery after a torn write, loss.png."""

from __future__ import annotations

import json

import math
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from mcdenoise.models.registry import build_model, synthetic_batch
from mcdenoise.train.checkpoint import latest_checkpoint, load_checkpoint, prune_checkpoints, save_checkpoint
from mcdenoise.train.config import ConfigError, TrainConfig, check_resume_config
from mcdenoise.train.losses import LOSSES, Loss, get_loss
from mcdenoise.train.trainer import Trainer
from mcdenoise.train.optim import lr_at
from mcdenoise.train.runlog import COLUMNS, MetricsLog, plot_loss, read_metrics


def _pair(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    pred = torch.rand((2, 3, 5, 5), generator=g, dtype=torch.float64) * 3 - 0.5
    target = torch.rand((2, 3, 5, 5), generator=g, dtype=torch.float64) * 3
    return pred, target


def _guide(loss: Loss, like: torch.Tensor) -> torch.Tensor | None:
    """A positive input-side guide for a guided loss (None otherwise)."""
    return like.detach().abs() + 0.05 if loss.guided else None


@pytest.mark.parametrize("name", sorted(LOSSES))
def test_loss_zero_at_target_positive_elsewhere_finite_gradient(name: str) -> None:
    """Catches a loss with an offset, a sign error, or a NaN gradient for negative predictions
    (x / (1 + x) and log(1 + x) have poles at x = -1)."""
    loss = get_loss(name)
    pred, target = _pair()
    guide = _guide(loss, pred)
    assert float(loss(target.clone(), target, guide)) == 0.0
    pred = pred.clone().requires_grad_(True)
    bad = pred.detach().clone()
    bad[0, 0, 0, 0] = -1.0  # at the pole of the naive tonemap
    bad.requires_grad_(True)
    for p in (pred, bad):
        value = loss(p, target, guide)
        assert value.ndim == 0 and float(value.detach()) > 0
        (g,) = torch.autograd.grad(value, p)
        assert torch.isfinite(g).all()
    with pytest.raises(ValueError, match="prediction"):
        loss(pred[:, :2], target)


@pytest.mark.parametrize("name", sorted(LOSSES))
def test_noisy_target_unbiasedness_flag_is_honest(name: str) -> None:
    """Catches a loss marked unbiased for noisy targets whose expected gradient against
    ``y +/- n`` differs from the gradient against ``y`` (relMSE with the target in the
    denominator, for one), and a biased mark on a loss that would be fine."""
    loss = get_loss(name)
    pred, clean = _pair(1)
    guide = _guide(loss, pred)  # from the input: the same whatever the target
    if guide is not None:  # dim enough that every exception ratio (10, 100) fires on some targets
        guide = guide * 1e-3
    noise = torch.rand_like(clean) * clean  # keeps targets >= 0, large enough to cross pred
    grads = []
    for t in (clean, clean + noise, clean - noise):
        p = pred.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(loss(p, t, guide), p)
        grads.append(g)
    expected = (grads[1] + grads[2]) / 2
    same = torch.allclose(expected, grads[0], rtol=1e-9, atol=1e-12)
    assert same == loss.unbiased_for_noisy_target, (name, float((expected - grads[0]).abs().max()))


def test_relmse_ref_loss_is_the_evaluation_metric() -> None:
    """Catches `relmse_ref` drifting from the relMSE that eval reports (its denominator taken from
    the prediction as `relmse` does, another eps, or a sum instead of a mean), which would make
    it train toward something other than the figure it is meant to lower."""
    from mcdenoise.eval.metrics import relmse

    pred, target = _pair(2)
    want = relmse(pred, target)  # (B, 3, H, W): the mean over images of each image's mean
    got = get_loss("relmse_ref")(pred, target)
    assert torch.allclose(got, torch.as_tensor(want, dtype=got.dtype), rtol=1e-12, atol=0)
    assert not torch.allclose(get_loss("relmse")(pred, target), got, rtol=1e-3, atol=0)


def test_loss_sum_is_the_weighted_sum_of_its_terms() -> None:
    """Catches a sum that drops a term or its weight, marks itself unbiased when a term is not,
    or accepts a misspelt term, a zero or negative weight instead of refusing it."""
    pred, target = _pair(3)
    mixed = get_loss("smape+0.1*relmse_ref")
    want = get_loss("smape")(pred, target) + 0.1 * get_loss("relmse_ref")(pred, target)
    assert torch.allclose(mixed(pred, target), want, rtol=1e-12, atol=0)
    assert not mixed.unbiased_for_noisy_target
    assert get_loss("l2+2*relmse").unbiased_for_noisy_target
    for bad in ("smape+0.1*relmse_rf", "smape+0*relmse_ref", "smape+-1*relmse_ref", "smape+x*l1", "smape+"):
        with pytest.raises(KeyError, match="unknown loss"):
            get_loss(bad)
    with pytest.raises(ConfigError, match="unknown loss"):
        TrainConfig(model="wskp", data="x", loss="smape+0.1*relmse_rf").check()


def test_relmse_in_optimum_is_the_conditional_mean_and_relmse_ref_is_darker() -> None:
    """Catches a guided loss whose weight leaks the target (its best constant answer to an uncertain
    pixel would then sit below the mean: the dark bias of `relmse_ref`), and checks that
    `relmse_ref` keeps that bias, which is why the guided loss exists. One input pixel whose
    reference is 0.1 or 10 with equal odds: the expected gradient at the mean must vanish."""
    targets = torch.tensor([0.1, 10.0], dtype=torch.float64).view(2, 1, 1, 1).expand(2, 3, 4, 4)
    guide = torch.full_like(targets, 1.0)  # the same input behind both outcomes, within 10x of both
    mean = targets.mean(0, keepdim=True).expand_as(targets)
    for name, unbiased in (("relmse_in", True), ("relmse_ref", False)):
        x = mean.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(get_loss(name)(x, targets, guide), x)
        expected = g.sum(0)  # over the two equally likely outcomes of each pixel
        if unbiased:
            assert float(expected.abs().max()) < 1e-12, name
        else:  # a positive expected gradient at the mean: the optimum lies below it
            assert float(expected.min()) > 1e-4, name


def test_relmse_in_exception_is_dark_where_it_fires_and_the_wide_ratio_fires_later() -> None:
    """Catches an exception ratio that is not the one documented (the wide loss must stay unbiased
    where the target is 20x the guide, and `relmse_in` must not: its weight then comes from the
    target, which is the dark bias campaign 19 measures), and a wide exception that no longer caps
    a light every sample missed (its cost must be WIDE_GUIDE_RATIO^2, not 1e10)."""
    from mcdenoise.train.losses import WIDE_GUIDE_RATIO

    targets = torch.tensor([0.1, 20.0], dtype=torch.float64).view(2, 1, 1, 1).expand(2, 3, 4, 4)
    guide = torch.full_like(targets, 1.0)  # the brighter outcome is 20x the guide
    mean = targets.mean(0, keepdim=True).expand_as(targets)
    for name, unbiased in (("relmse_in_wide", True), ("relmse_in", False)):
        x = mean.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(get_loss(name)(x, targets, guide), x)
        expected = g.sum(0)
        if unbiased:
            assert float(expected.abs().max()) < 1e-12, name
        else:
            assert float(expected.min()) > 1e-4, name
    lit = torch.full((1, 3, 2, 2), 1e6)
    cost = float(get_loss("relmse_in_wide")(torch.zeros_like(lit), lit, torch.zeros_like(lit)))
    assert cost == pytest.approx(WIDE_GUIDE_RATIO ** 2, rel=1e-6)


def test_lowpass_l1_charges_block_brightness_and_ignores_what_averages_out() -> None:
    """Catches a low-pass term that pools the wrong block (or not at all), so that it charges noise
    the pixel losses already cost, or misses a uniform darkening, which is what it exists to charge;
    and partial border blocks averaged over pixels outside the image (a crop not a multiple of 8)."""
    from mcdenoise.train.losses import LOWPASS_BLOCK

    loss = get_loss("lowpass_l1")
    g = torch.Generator().manual_seed(5)
    target = torch.rand((2, 3, 4 * LOWPASS_BLOCK, 4 * LOWPASS_BLOCK), generator=g, dtype=torch.float64) + 1.0
    # +-0.5 in a checkerboard: every 8x8 block's mean is unchanged, though each pixel is off by 0.5.
    yy, xx = torch.meshgrid(torch.arange(target.shape[-2]), torch.arange(target.shape[-1]), indexing="ij")
    checker = ((yy + xx) % 2 * 2 - 1).to(target) * 0.5
    assert float(loss(target + checker, target)) == pytest.approx(0.0, abs=1e-12)
    assert float(get_loss("smape")(target + checker, target)) > 0.1
    # 5% darker everywhere: each block costs 0.05 * mean / (mean + 0.01).
    blocks = F.avg_pool2d(target, LOWPASS_BLOCK)
    want = float((0.05 * blocks / (blocks + 0.01)).mean())
    assert float(loss(0.95 * target, target)) == pytest.approx(want, rel=1e-9)
    # 12 px: the border blocks are 8x4, 4x8 and 4x4 means of the pixels that exist.
    small = torch.ones((1, 1, 12, 12), dtype=torch.float64)
    pred = small.clone()
    pred[..., 8:, 8:] = 0.0  # the 4x4 corner block is black: cost 1 / 1.01 on 1 of 4 blocks
    assert float(loss(pred, small)) == pytest.approx(0.25 / 1.01, rel=1e-9)


def test_input_guide_is_a_firefly_proof_local_mean_without_gradient() -> None:
    """Catches a guide that is not the sample mean (a constant image must give itself), that
    spreads one firefly or one highlight pixel onto its neighbours (a box blur would, lowering the
    weight exactly where halos are), that erases a one-pixel light (a median alone would, giving it
    the weight 1 / 0.01 of black: campaign 18's first try, loss ~3500), that carries a gradient,
    and a guided loss called without its guide or with a guide of the wrong shape."""
    from mcdenoise.train.losses import input_guide

    samples = torch.full((1, 4, 3, 6, 6), 0.2, dtype=torch.float64)
    samples[0, :, 1] = 0.4  # green twice as bright: per channel
    clean = samples.mean(1).float()
    assert torch.allclose(input_guide(samples), clean)
    samples[0, 0, :, 2, 3] = 1000.0  # one firefly in one sample
    guide = input_guide(samples.requires_grad_(True))
    want = clean.clone()
    want[..., 2, 3] = samples.detach()[:, :, :, 2, 3].mean(1).float()  # only the firefly's own pixel
    assert torch.allclose(guide, want, rtol=1e-6, atol=0) and not guide.requires_grad
    pixels = torch.zeros((1, 3, 5, 5))
    pixels[..., 0, 0] = 50.0  # a one-pixel light in a corner (replicate border): its own, not its neighbours'
    assert torch.equal(input_guide(pixels), pixels)
    with pytest.raises(ValueError, match="guide"):
        get_loss("relmse_in")(pixels, pixels)
    with pytest.raises(ValueError, match="guide"):
        get_loss("smape+0.1*relmse_in")(pixels, pixels, pixels[:, :1])
    assert get_loss("smape+0.1*relmse_in").guided and not get_loss("smape").guided
    # A light every sample missed (guide 0, reference 1e4) costs about GUIDE_RATIO^2 at black, not 1e10.
    lit = torch.full((1, 3, 2, 2), 1e4)
    assert float(get_loss("relmse_in")(torch.zeros_like(lit), lit, torch.zeros_like(lit))) == pytest.approx(100.0, rel=1e-6)


def test_guided_loss_refused_for_models_it_cannot_weigh() -> None:
    """Catches KPCN's per-branch phase (log/albedo domains) silently weighted by radiance."""
    from mcdenoise.models.registry import build_model
    from mcdenoise.train.trainer import Trainer

    cfg = TrainConfig(model="kpcn", data="x", loss="relmse_in").resolved(build_model("kpcn").input_kind)
    with pytest.raises(ConfigError, match="relmse_in"):
        Trainer(build_model("kpcn"), cfg, torch.device("cpu"))


def test_noisy_target_refuses_biased_loss_in_one_line() -> None:
    """Catches `--target noisy` silently training towards a biased optimum."""
    cfg = TrainConfig(model="wskp", data="x", target="noisy", loss="smape")
    with pytest.raises(ConfigError) as err:
        cfg.resolved("pixels")
    assert "biased" in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="biased"):
        TrainConfig(model="wskp", data="x", target="noisy").resolved("pixels")  # smape is wskp's default
    ok = TrainConfig(model="kpcn", data="x", target="noisy", loss="relmse").resolved("pixels")
    assert ok.branch_fraction == 0.0  # the log-domain branch phase is biased too
    assert TrainConfig(model="kpcn", data="x").resolved("pixels").branch_fraction == 0.8


def test_defaults_follow_the_papers() -> None:
    """Catches a model family trained with another paper's loss."""
    want = {"kpcn": "l1", "dpcn": "l1", "sbmc": "tonemapped_l2", "pixel_splat": "tonemapped_l2", "layer": "smape",
            "layer_optimized": "smape", "wskp": "smape"}
    for model, loss in want.items():
        assert TrainConfig(model=model, data="x").resolved("pixels").loss == loss
    assert TrainConfig(model="sbmc", data="x").resolved("samples").spp_range == (2, 8)


def test_schedule_warmup_then_cosine() -> None:
    """Catches an off-by-one that starts at lr 0 (a wasted step) or a decay that misses its floor."""
    cfg = TrainConfig(model="wskp", data="x", steps=100, lr=1e-3, warmup=0.1, min_lr_fraction=0.05).resolved("pixels")
    lrs = [lr_at(t, cfg) for t in range(100)]
    assert lrs[0] == pytest.approx(1e-4) and lrs[9] == pytest.approx(1e-3)
    assert all(b > a for a, b in zip(lrs[:10], lrs[1:10]))
    assert all(b <= a for a, b in zip(lrs[10:], lrs[11:]))
    assert lrs[-1] == pytest.approx(5e-5)
    step = TrainConfig(model="wskp", data="x", steps=100, lr=1.0, warmup=0, schedule="step").resolved("pixels")
    assert [lr_at(t, step) for t in (0, 49, 50, 74, 75, 99)] == pytest.approx([1, 1, 0.1, 0.1, 0.01, 0.01])


def test_non_finite_loss_is_skipped_and_counted() -> None:
    """Catches a NaN batch corrupting the weights, Adam's moments or WSKP's BatchNorm running
    statistics (updated in the forward pass) instead of being dropped."""
    torch.manual_seed(0)
    model = build_model("wskp")
    cfg = TrainConfig(model="wskp", data="x", steps=10, warmup=0).resolved("pixels")
    tr = Trainer(model, cfg, torch.device("cpu"))
    batch = synthetic_batch(model, batch=2, height=12, width=12)
    batch["target"] = batch["radiance"] * 0.5
    bad = dict(batch, radiance=batch["radiance"].clone())
    bad["radiance"][0, 0, 3, 3] = float("nan")
    before = {k: v.clone() for k, v in model.state_dict().items()}
    out = tr.step(bad, 0)
    assert out.skipped and not math.isfinite(out.loss)
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())
    assert not tr.optimizer.state  # Adam never saw the bad gradient
    ok = tr.step(batch, 1)
    assert not ok.skipped and math.isfinite(ok.loss)
    assert any(not torch.equal(before[k], v) for k, v in model.state_dict().items())


def test_checkpoint_round_trip_weights_only(tmp_path: Path) -> None:
    """Catches a checkpoint that needs unpickling, misses Adam's state, or whose pruning deletes
    the newest or a kept-periodic folder."""
    torch.manual_seed(0)
    model = build_model("wskp")
    cfg = TrainConfig(model="wskp", data="x", steps=10).resolved("pixels")
    tr = Trainer(model, cfg, torch.device("cpu"))
    batch = synthetic_batch(model, batch=2, height=12, width=12)
    batch["target"] = batch["radiance"]
    tr.step(batch, 0)
    for step in (2, 4, 6):
        save_checkpoint(tmp_path, step, model, tr.state(step, skipped=1))
    (tmp_path / "checkpoints" / ".step_00000008.tmp-1-abcd").mkdir()  # a killed write
    prune_checkpoints(tmp_path, keep_every=4)
    names = sorted(p.name for p in (tmp_path / "checkpoints").iterdir())
    assert names == ["step_00000004", "step_00000006"]
    ck = latest_checkpoint(tmp_path)
    assert ck is not None and ck.step == 6
    torch.load(ck.path / "state.pt", weights_only=True)
    torch.manual_seed(1)
    other = build_model("wskp")
    tr2 = Trainer(other, cfg, torch.device("cpu"))
    st = load_checkpoint(ck, other)
    assert tr2.load_state(st) == 1 and st["step"] == 6
    for k, v in model.state_dict().items():
        assert torch.equal(v, other.state_dict()[k])
    a, b = tr.optimizer.state_dict()["state"], tr2.optimizer.state_dict()["state"]
    assert a.keys() == b.keys() and all(torch.equal(a[i]["exp_avg"], b[i]["exp_avg"]) for i in a)


def test_metrics_log_drops_rows_after_checkpoint_and_torn_line(tmp_path: Path) -> None:
    """Catches a resumed run keeping rows from after its checkpoint (duplicated steps) or a torn
    last line from the kill (a bogus row)."""
    log = MetricsLog(tmp_path, 0, tensorboard=False)
    for s in range(1, 6):
        log.write({"step": s, "phase": "image", "loss": 1.0 / s, "lr": 1e-3})
    log.close()
    with open(tmp_path / "metrics.csv", "a") as f:
        f.write("1")  # a torn "1x,..." row
    assert [r["step"] for r in read_metrics(tmp_path / "metrics.csv")] == ["1", "2", "3", "4", "5"]
    log = MetricsLog(tmp_path, 3, tensorboard=False)
    log.write({"step": 4, "phase": "image", "loss": 0.5})
    log.close()
    rows = read_metrics(tmp_path / "metrics.csv")
    assert [r["step"] for r in rows] == ["1", "2", "3", "4"] and rows[-1]["loss"] == "0.5"
    assert (tmp_path / "metrics.csv").read_text().splitlines()[0] == ",".join(COLUMNS)
    png = plot_loss(tmp_path / "metrics.csv", tmp_path / "loss.png")
    assert png is not None and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_loss_png_with_and_without_matplotlib(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Catches a loss.png that breaks on either drawing path (labelled matplotlib figure, or the
    numpy fallback where matplotlib is missing), or a half-written PNG left behind."""
    import sys

    log = MetricsLog(tmp_path, 0, tensorboard=False)
    for s in range(1, 41):
        log.write({"step": s, "phase": "branches" if s <= 30 else "image", "loss": 1.0 / s, "lr": 1e-3,
                   **({"val_relmse": 0.5 / s} if s % 10 == 0 else {})})
    log.close()
    for label in ("matplotlib", "fallback"):
        if label == "fallback":
            monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
        png = plot_loss(tmp_path / "metrics.csv", tmp_path / f"{label}.png")
        assert png is not None and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", label
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fallback.png", "matplotlib.png", "metrics.csv"]


def test_loss_png_axes_are_logarithmic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Bug caught (issue 18): loss.png drew a loss swinging between 0.1 and 1000 on a linear axis,
    where only the spikes could be read; the loss axis and the validation axis are both log."""
    import matplotlib.figure

    scales: list[list[str]] = []
    save = matplotlib.figure.Figure.savefig

    def spy(fig: matplotlib.figure.Figure, *a: object, **k: object) -> None:
        scales.append([ax.get_yscale() for ax in fig.axes])
        save(fig, *a, **k)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", spy)
    log = MetricsLog(tmp_path, 0, tensorboard=False)
    for s in range(1, 41):
        log.write({"step": s, "phase": "image", "loss": 1000.0 if s % 7 == 0 else 0.1 * s, "lr": 1e-3,
                   **({"val_relmse": 15.0 / s} if s % 10 == 0 else {})})
    log.close()
    assert plot_loss(tmp_path / "metrics.csv", tmp_path / "loss.png") is not None
    assert scales == [["log", "log"]]


def test_resume_refuses_changed_settings() -> None:
    """Catches a resume that silently continues with another learning rate or dataset."""
    a = {"train": TrainConfig(model="kpcn", data="d", lr=1e-3).to_json(), "manifest_sha256": "x", "model_config": {}}
    b = {"train": TrainConfig(model="kpcn", data="elsewhere", lr=1e-3, workers=7).to_json(), "manifest_sha256": "x",
         "model_config": {}}
    check_resume_config(a, b, Path("run/config.json"))  # data path and workers do not change the math
    c = dict(b, train=TrainConfig(model="kpcn", data="d", lr=2e-3).to_json())
    with pytest.raises(ConfigError) as err:
        check_resume_config(a, c, Path("run/config.json"))
    assert "lr" in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="manifest"):
        check_resume_config(a, dict(b, manifest_sha256="y"), Path("run/config.json"))


def test_exposure_setting_round_trips_and_guards_a_resume() -> None:
    """Catches the exposure range lost in config.json (a resumed run would train without it), a
    resume that changes it silently, and runs from before the option refusing to resume."""
    import json

    cfg = TrainConfig(model="kpcn", data="d", exposure=(0.1, 10.0))
    back = TrainConfig.from_json(json.loads(json.dumps(cfg.to_json())))
    assert back.exposure == (0.1, 10.0) and back == cfg
    doc = lambda c: {"train": c.to_json(), "manifest_sha256": "x", "model_config": {}}  # noqa: E731
    with pytest.raises(ConfigError, match="exposure"):
        check_resume_config(doc(cfg), doc(TrainConfig(model="kpcn", data="d")), Path("run/config.json"))
    old = TrainConfig(model="kpcn", data="d").to_json()
    del old["exposure"]  # a config.json written before the option existed
    check_resume_config({"train": old, "manifest_sha256": "x", "model_config": {}},
                        doc(TrainConfig(model="kpcn", data="d")), Path("run/config.json"))


def test_resume_accepts_a_model_field_added_since_the_run_was_saved() -> None:
    """Catches every run saved before a model-configuration field existed (``autoexposure``) being
    refused on resume, and a real change of that field slipping through."""
    import dataclasses as dc

    from mcdenoise.models import build_model

    cur = json.loads(json.dumps(dc.asdict(build_model("kpcn", "pixel").config)))
    train = TrainConfig(model="kpcn", data="d").to_json()
    old = {k: v for k, v in cur.items() if k != "autoexposure"}
    doc = lambda mc: {"train": train, "manifest_sha256": "x", "model_config": mc}  # noqa: E731
    check_resume_config(doc(old), doc(cur), Path("run/config.json"))
    with pytest.raises(ConfigError, match="model's configuration"):
        check_resume_config(doc(old), doc(dict(cur, autoexposure=0.18)), Path("run/config.json"))
    with pytest.raises(ConfigError, match="model's configuration"):
        check_resume_config(doc(dict(old, channels=7)), doc(cur), Path("run/config.json"))


def test_cli_help_names_every_loss() -> None:
    """Catches a loss added to the registry but missing from `mcdenoise train --help` (the parser
    lists them by hand so that building it never imports torch)."""
    import argparse

    from mcdenoise.cli.train import add_parser

    p = argparse.ArgumentParser()
    add_parser(p)
    help_text = next(a.help for a in p._actions if "--loss" in a.option_strings)
    assert sorted(n.strip(" ,") for n in help_text.split("(")[0].replace(" or ", ", ").split(",")) == sorted(LOSSES)


def test_metrics_mirrored_to_tensorboard_when_installed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Catches the TensorBoard path breaking unseen on machines without tensorboard (ours): a
    stand-in SummaryWriter must receive every finite scalar, with validation under val/, and a
    resume must purge the steps after the checkpoint."""
    import sys
    import types

    calls: list[tuple] = []

    class FakeWriter:
        def __init__(self, logdir: str, purge_step: int | None = None) -> None:
            calls.append(("init", Path(logdir).name, purge_step))

        def add_scalar(self, tag: str, value: float, step: int) -> None:
            calls.append((tag, value, step))

        def close(self) -> None:
            calls.append(("close",))

    fake = types.ModuleType("torch.utils.tensorboard")
    fake.SummaryWriter = FakeWriter  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", fake)
    log = MetricsLog(tmp_path, 7)
    log.write({"step": 8, "phase": "image", "loss": 0.25, "lr": 1e-3, "grad_norm": float("nan"), "val_relmse": 0.5})
    log.close()
    assert calls[0] == ("init", "tensorboard", 8)
    assert ("loss", 0.25, 8) in calls and ("val/relmse", 0.5, 8) in calls and ("lr", 1e-3, 8) in calls
    assert not any(c[0] == "grad_norm" for c in calls) and calls[-1] == ("close",)
