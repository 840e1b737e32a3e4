"""Fine-tuning from weights (--init) and extending a finished run (--resume --steps N), issue 19."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from mcdenoise.cli.main import main
from mcdenoise.train.runlog import read_metrics
from train_tiny_data import make_tiny_dataset

RUN = ["--model", "wskp", "--crop", "16", "--batch", "2", "--workers", "0", "--val-every", "0", "--no-progress",
       "--checkpoint-every", "2", "--sampling", "uniform", "--threads", "1"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_tiny_dataset(tmp_path_factory.mktemp("tiny") / "data")


def test_init_starts_from_the_given_weights(tiny: Path, tmp_path: Path) -> None:
    """Catches --init being ignored (training from random weights) or loaded after the optimizer
    took its first step: with a negligible learning rate the run's parameters stay the init's
    (batch-norm statistics still move, so they are left out)."""
    base = ["train", *RUN, "--data", str(tiny)]
    assert main([*base, "--out", str(tmp_path / "a"), "--steps", "2"]) == 0
    src = tmp_path / "a" / "model.safetensors"
    assert main([*base, "--out", str(tmp_path / "b"), "--steps", "2", "--init", str(src), "--lr", "1e-30"]) == 0
    a, b = load_file(str(src)), load_file(str(tmp_path / "b" / "model.safetensors"))
    params = [k for k in a if "running_" not in k and "num_batches" not in k]
    assert a.keys() == b.keys() and params
    assert all(torch.allclose(a[k], b[k], rtol=1e-6, atol=1e-20) for k in params)
    saved = json.loads((tmp_path / "b" / "config.json").read_text())
    assert saved["train"]["init"] == str(src)


def test_init_refuses_another_model(tiny: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Catches kpcn weights silently loaded (or crashing) into a wskp run."""
    rc = main(["train", *RUN, "--data", str(tiny), "--out", str(tmp_path / "c"), "--steps", "1", "--init", "kpcn"])
    assert rc == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "kpcn" in err and "wskp" in err


def test_init_takes_a_run_whose_overrides_equal_the_asked_preset(tiny: Path, tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture) -> None:
    """Catches: --init judging the preset by name alone. Campaign 13's GPU run named preset small
    with --model-overrides that equal preset medium; seeding a medium run from it was refused. A
    run whose architecture differs from the asked preset must still be refused, in one line."""
    from mcdenoise.models.registry import build_model

    base = ["train", *RUN, "--data", str(tiny), "--steps", "1"]
    # The fields in which preset paper3 differs from small: a small run with them is paper3.
    want, small = build_model("wskp", "paper3").config, build_model("wskp", "small").config
    over = {k: v for k, v in vars(want).items() if getattr(small, k) != v}
    assert over
    assert main([*base, "--out", str(tmp_path / "a"), "--model-overrides", json.dumps(over)]) == 0
    assert main([*base, "--out", str(tmp_path / "b"), "--preset", "paper3", "--init", str(tmp_path / "a")]) == 0
    capsys.readouterr()
    assert main([*base, "--out", str(tmp_path / "c"), "--preset", "paper", "--init", str(tmp_path / "a")]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "pass --preset small" in err


def test_resume_with_more_steps_extends_a_finished_run(tiny: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Catches a finished run that cannot be extended (refused as a config change) or that restarts
    from step 0; fewer steps than done are still refused."""
    out = tmp_path / "run"
    base = ["train", *RUN, "--data", str(tiny), "--out", str(out)]
    assert main([*base, "--steps", "2"]) == 0
    assert main([*base, "--steps", "4", "--resume"]) == 0
    assert "extending the run from 2 to 4 steps" in capsys.readouterr().err
    assert [int(r["step"]) for r in read_metrics(out / "metrics.csv")] == [1, 2, 3, 4]
    assert json.loads((out / "config.json").read_text())["train"]["steps"] == 4
    assert main([*base, "--steps", "3", "--resume"]) == 1


def test_validation_prints_the_noisy_baseline_and_reads_val_data(tiny: Path, tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture) -> None:
    """Catches a validation figure printed with nothing to compare it to (issue 18: 'relmse 14.96'
    alone), --val-data being ignored, and a resume that does not say where it resumed."""
    out = tmp_path / "v"
    base = ["train", *RUN, "--val-every", "2", "--data", str(tiny), "--out", str(out), "--val-data", str(tiny)]
    assert main([*base, "--steps", "2"]) == 0
    err = capsys.readouterr().err
    assert f"of {tiny}; the noisy input scores relmse" in err
    assert main([*base, "--steps", "4", "--resume"]) == 0
    assert "resuming at step 2 of 4" in capsys.readouterr().err
    assert main(["train", *RUN, "--data", str(tiny), "--out", str(tmp_path / "w"), "--steps", "1",
                 "--val-data", str(tmp_path / "nowhere")]) == 1
