"""Loading weights by name, run folder or file, and shipping a run with its model card."""

from __future__ import annotations

import argparse
import json
import shlex
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from mcdenoise.cli import dataset as dataset_cli
from mcdenoise.cli import train as train_cli
from mcdenoise.models import build_model, synthetic_batch
from mcdenoise.models import weights as W
from mcdenoise.models.ship import dataset_command, ship, train_command
from mcdenoise.render.procedural_dataset import DatasetConfig
from mcdenoise.train import train
from mcdenoise.train.checkpoint import state_dict_for_safetensors
from mcdenoise.train.config import RUNTIME_FIELDS, TrainConfig
from train_tiny_data import make_tiny_dataset


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished 3-step WSKP run whose model config differs from the preset (channels=6)."""
    root = tmp_path_factory.mktemp("weights")
    data = make_tiny_dataset(root / "data", size=24)
    cfg = TrainConfig(model="wskp", data=str(data), steps=3, batch=2, crop=16, workers=0, val_every=0,
                      threads=1, target="noisy", loss="relmse", spp_range=(2, 4), progress=False)
    out = root / "run"
    # A non-preset field proves that the run's saved config, not the preset, rebuilds the model.
    import mcdenoise.models.registry as reg

    entry = reg.MODELS["wskp"]
    orig = entry.presets["small"]
    entry.presets["small"] = lambda: __import__("dataclasses").replace(orig(), channels=6)
    try:
        train(cfg, out)
    finally:
        entry.presets["small"] = orig
    return out


def _out(model: torch.nn.Module) -> torch.Tensor:
    with torch.no_grad():
        return model(synthetic_batch(model, height=16, width=16))


def test_run_folder_rebuilds_the_saved_configuration(run: Path) -> None:
    """Bug caught: a resolver that builds the preset and loads weights of another shape (or silently
    ignores the run's model_config)."""
    model, info = W.load_denoiser(run)
    assert model.config.channels == 6 and info["source"] == "run" and info["step"] == 3
    assert not model.training


def test_shipped_weights_by_name_match_the_run(run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Bug caught: shipped weights that load into a fresh model (wrong file, non-strict load) or a
    card whose configuration is not applied; build_model(weights='shipped') must equal the run."""
    monkeypatch.setattr(W, "SHIPPED_DIR", tmp_path)
    w, c = ship(run, out_dir=tmp_path, docs=tmp_path / "TRAINING.md")
    trained, _ = W.load_denoiser(run)
    by_name = build_model("wskp", weights="shipped")
    by_resolver, info = W.load_denoiser("wskp")
    by_file, finfo = W.load_denoiser(w)  # the file alone names its model and configuration
    ref = _out(trained)
    for m in (by_name.eval(), by_resolver, by_file):
        torch.testing.assert_close(_out(m), ref, rtol=0, atol=0)
    assert info["source"] == "shipped" and finfo["source"] == "file"
    card = json.loads(c.read_text())
    assert card["model_config"]["channels"] == 6 and card["training"]["steps"] == 3
    import hashlib

    assert card["weights_sha256"] == hashlib.sha256(w.read_bytes()).hexdigest()
    doc = (tmp_path / "TRAINING.md").read_text()
    assert card["training"]["command"] in doc and "generated:shipped:wskp-small" in doc
    with pytest.raises(W.WeightsError, match="exist"):
        ship(run, out_dir=tmp_path)
    # A re-ship keeps the card's not_for (the automatic pick's per-source exclusions, measured on
    # renders the run knows nothing of); a forgotten one would hand Blender users a worse model.
    c.write_text(json.dumps({**card, "not_for": {"blender": "measured"}}))
    _, c2 = ship(run, out_dir=tmp_path, force=True)
    assert json.loads(c2.read_text())["not_for"] == {"blender": "measured"}


def test_ship_records_a_preset_only_when_the_run_equals_it(run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Bug caught: ``ship --preset`` naming weights after a preset whose architecture is not the
    run's (a card and file name that lie about the model), or losing the run's own command. The run
    trained ``small`` with channels=6; a preset with channels=6 may name it, one with 5 may not."""
    import dataclasses

    import mcdenoise.models.registry as reg

    monkeypatch.setattr(W, "SHIPPED_DIR", tmp_path)
    entry = reg.MODELS["wskp"]
    monkeypatch.setitem(entry.presets, "six", lambda: dataclasses.replace(entry.presets["small"](), channels=6))
    monkeypatch.setitem(entry.presets, "five", lambda: dataclasses.replace(entry.presets["small"](), channels=5))
    with pytest.raises(W.WeightsError, match="differs from preset 'five'.*channels") as e:
        ship(run, out_dir=tmp_path, preset="five")
    assert "\n" not in str(e.value) and not list(tmp_path.glob("*.safetensors"))
    w, c = ship(run, out_dir=tmp_path, preset="six")
    card = json.loads(c.read_text())
    assert w.name == "wskp-six.safetensors" and card["preset"] == "six"
    assert "'small'" in card["training"]["preset_note"] and "--model wskp" in card["training"]["command"]
    model, info = W.load_denoiser("wskp-six")
    assert info["preset"] == "six" and model.config.channels == 6


def test_missing_and_mismatched_weights_are_one_line_errors(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Bug caught: a KeyError/RuntimeError traceback (or a silent partial load) instead of an error
    that names the file."""
    monkeypatch.setattr(W, "SHIPPED_DIR", tmp_path)
    with pytest.raises(W.WeightsError, match="no shipped weights for model 'kpcn'"):
        W.load_denoiser("kpcn")
    bad = tmp_path / "x.safetensors"
    save_file(state_dict_for_safetensors(build_model("kpcn")), str(bad), metadata={"model": "wskp", "preset": "small"})
    with pytest.raises(W.WeightsError, match="do not fit") as e:
        W.load_denoiser(bad)
    assert str(bad) in str(e.value) and "\n" not in str(e.value)
    (tmp_path / "junk.safetensors").write_bytes(b"not a tensor file")
    with pytest.raises(W.WeightsError, match="not a readable"):
        W.load_denoiser(tmp_path / "junk.safetensors", model="wskp")
    with pytest.raises(W.WeightsError, match="neither"):
        W.load_denoiser("no-such-model")


def _parse(sub: object, cmd: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    sub.add_parser(p)  # type: ignore[attr-defined]
    argv = shlex.split(cmd)
    assert argv[0] == "mcdenoise"
    return p.parse_args(argv[2:])


def test_card_commands_parse_back_to_the_settings_that_ran(run: Path, tmp_path: Path) -> None:
    """Bug caught: a model card whose commands would not reproduce the weights (a misspelt flag, a
    dropped non-default setting such as --spp or --target)."""
    doc = json.loads((run / "config.json").read_text())
    args = _parse(train_cli, train_command(doc, "runs/x"))
    rebuilt = train_cli.config_from_args(args)
    t = doc["train"]
    got = {"model": args.model, "steps": args.steps, "batch": args.batch, "crop": args.crop, "target": args.target,
           "loss": args.loss, "spp_range": list(args.spp) if args.spp else None, "lr": args.lr}
    for k, v in got.items():
        assert v == t[k], (k, v, t[k])
    a = rebuilt.to_json()
    keep = [k for k in a if k not in RUNTIME_FIELDS]
    assert {k: a[k] for k in keep} == {k: t[k] for k in keep}

    cfg = DatasetConfig(count=7, seed=3, spp=16, ref_spp=0, width=64, height=48, views=2, fractions=(0.8, 0.2, 0.0),
                        variant="cuda_ad_rgb")
    (tmp_path / "dataset.json").write_text(json.dumps(cfg.to_json()))
    ns = _parse(dataset_cli, dataset_command(tmp_path))
    assert (ns.count, ns.seed, ns.spp, ns.ref_spp, ns.size, ns.views, ns.split) == (7, 3, 16, 0, "64x48", 2, "0.8,0.2,0")
    assert ns.variant == "cuda_ad_rgb"  # issue 18: the card's command omitted the variant


def test_every_changed_setting_reaches_the_card_command(run: Path, tmp_path: Path) -> None:
    """Bug caught (issue 18): settings without a `train` flag (min_lr_fraction, model_overrides)
    silently dropped from a card's command, and a rich-world dataset stated as a classic one."""
    doc = json.loads((run / "config.json").read_text())
    doc["train"].update(min_lr_fraction=0.2, model_overrides={"channels": 6}, init="kpcn", val_data="data/v", warmup=0.1)
    args = _parse(train_cli, train_command(doc, "runs/x"))
    a = train_cli.config_from_args(args).to_json()
    for k in ("min_lr_fraction", "model_overrides", "init", "val_data", "warmup"):
        assert a[k] == doc["train"][k], k
    cfg = DatasetConfig(count=2, world="rich", max_depth=8, variant="llvm_ad_rgb")
    (tmp_path / "dataset.json").write_text(json.dumps(cfg.to_json()))
    ns = _parse(dataset_cli, dataset_command(tmp_path))
    assert (ns.world, ns.max_depth) == ("rich", 8)


def test_non_finite_weights_are_refused(tmp_path: Path, capfd: pytest.CaptureFixture) -> None:
    """Catches issue 22 item 5: NaN weights denoised to an all-NaN image with rc 0; loading them must
    be a one-line error naming the file (Python API and CLI)."""
    torch.manual_seed(0)
    state = state_dict_for_safetensors(build_model("wskp"))
    first = next(k for k, v in state.items() if v.is_floating_point())
    state[first].view(-1)[0] = float("nan")
    bad = tmp_path / "nan.safetensors"
    save_file(state, str(bad), metadata={"model": "wskp", "preset": "small"})
    with pytest.raises(W.WeightsError, match="non-finite") as e:
        W.load_denoiser(bad)
    assert str(bad) in str(e.value) and "\n" not in str(e.value)
    from mcdenoise.cli.main import main
    from mcdenoise.io.exr import write_exr_raw

    rng = __import__("numpy").random.default_rng(0)
    src = tmp_path / "in.exr"
    write_exr_raw(src, {c: rng.random((16, 16)).astype("float32") for c in
                        ("R", "G", "B", "albedo.R", "albedo.G", "albedo.B", "normal.X", "normal.Y", "normal.Z", "depth.Y")})
    capfd.readouterr()
    assert main(["denoise", str(src), "-o", str(tmp_path / "o.exr"), "--model", str(bad)]) == 1
    err = [ln for ln in capfd.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "nan.safetensors" in err[0] and "non-finite" in err[0], err
    assert not (tmp_path / "o.exr").exists()


def test_weights_file_and_config_errors_are_one_line(tmp_path: Path) -> None:
    """Catches issue 22 item 9's weights cases: `--model /missing.safetensors` said "does not name
    its model"; malformed model_config metadata and a JSON list as a run's config.json gave tracebacks."""
    with pytest.raises(W.WeightsError, match="no such weights file"):
        W.load_denoiser(tmp_path / "missing.safetensors")
    state = state_dict_for_safetensors(build_model("wskp"))
    for text, needle in (("{not json", "malformed model_config"), ("[1, 2]", "must be a JSON object")):
        f = tmp_path / "w.safetensors"
        save_file(state, str(f), metadata={"model": "wskp", "preset": "small", "model_config": text})
        with pytest.raises(W.WeightsError, match=needle) as e:
            W.load_denoiser(f)
        assert str(f) in str(e.value)
    run = tmp_path / "run"
    run.mkdir()
    for doc in ([1, 2], {"train": [1]}, {"train": {"model": "wskp"}, "model_config": [3]}):
        (run / "config.json").write_text(json.dumps(doc))
        with pytest.raises(W.WeightsError, match="config.json") as e:
            W.load_denoiser(run)
        assert "\n" not in str(e.value)


def test_a_run_folder_is_chosen_and_never_cached(run: Path) -> None:
    """Bug caught: the prepared-model cache of `choose_model` (repeated API calls) raised a
    NameError for a run folder (`mcdenoise denoise --model runs/x`), and a run folder must be
    loaded afresh each time (its checkpoint moves while it trains)."""
    import numpy as np

    from mcdenoise.infer.choose import choose_model
    from mcdenoise.infer.sources import from_arrays

    c = np.ones((3, 8, 8), np.float32)
    inputs = from_arrays(c, albedo=c, normal=c, depth=c[:1])
    first, info = choose_model(inputs, str(run), precision="float32")
    again, _ = choose_model(inputs, str(run), precision="float32")
    assert info["source"] == "run" and first.config.channels == 6 and again is not first


def test_shipped_weights_load_by_their_file_name() -> None:
    """Catches a shipped preset other than ``small`` (kpcn-pixel, combine-ens) that no command can
    name (``--model kpcn`` means kpcn-small), and a typo'd preset that falls back to another."""
    from mcdenoise.models.weights import WeightsError, load_denoiser, shipped

    for sw in shipped():
        net, info = load_denoiser(f"{sw.name}-{sw.preset}")
        assert (info["name"], info["preset"], info["source"]) == (sw.name, sw.preset, "shipped")
        assert info["label"] == f"{sw.name}-{sw.preset}" and Path(info["weights"]) == sw.weights
    with pytest.raises(WeightsError, match="preset 'nope'"):
        load_denoiser("kpcn-nope")


def test_average_weights_mixes_tensors_and_keeps_a_loadable_file(run: Path, tmp_path: Path) -> None:
    """Catches scripts/average_weights.py writing anything but sum_i w_i theta_i (a weight applied
    twice or to one input only), losing the model configuration (the result would not load by
    file), or averaging models whose tensors differ in shape instead of refusing them."""
    import subprocess
    import sys

    from safetensors import safe_open
    from safetensors.torch import load_file

    script = Path(__file__).resolve().parent.parent / "scripts" / "average_weights.py"
    src = load_file(str(run / "model.safetensors"))
    with safe_open(str(run / "model.safetensors"), "pt") as f:
        meta = f.metadata()
    other = {k: (v + 1.0 if v.is_floating_point() else v) for k, v in src.items()}
    save_file(other, str(tmp_path / "other.safetensors"), metadata=meta)
    out = tmp_path / "mix.safetensors"
    subprocess.run([sys.executable, str(script), str(out), str(run), str(tmp_path / "other.safetensors"),
                    "--weights", "0.25", "0.75", "--set", "channels=6"], check=True, capture_output=True)
    mix = load_file(str(out))
    for k, v in src.items():
        if v.is_floating_point():
            torch.testing.assert_close(mix[k], v + 0.75, rtol=0, atol=1e-6)
    model, info = W.load_denoiser(str(out))
    assert info["name"] == "wskp" and model.config.channels == 6
    bad = dict(other)
    k = next(k for k, v in bad.items() if v.is_floating_point() and v.dim() > 1)
    bad[k] = bad[k][:1]
    save_file(bad, str(tmp_path / "bad.safetensors"), metadata=meta)
    proc = subprocess.run([sys.executable, str(script), str(tmp_path / "x.safetensors"), str(run),
                           str(tmp_path / "bad.safetensors")], capture_output=True, text=True)
    assert proc.returncode != 0 and "shape" in proc.stderr and not (tmp_path / "x.safetensors").exists()
