"""`mcdenoise models`: WSKP is listed in both its training and its inference (fused) form."""

from __future__ import annotations

import json

import pytest

from mcdenoise.cli import main as cli


def test_wskp_listing_shows_training_and_inference_forms(capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 8 item 10: the listing showed only WSKP's training form (38,824 parameters,
    0.08 MFLOP/px) while the paper times the re-parameterised network (27,382, 0.055 MFLOP/px).
    Both must appear, in the JSON and in the text, with the literal counts of the paper preset;
    models without a fused form get no inference entry."""
    only = ["--model", "wskp", "--model", "wskp_mr", "--preset", "paper", "--flops"]
    assert cli.main(["models", "--json", *only]) == 0
    rows = {r["name"]: r for r in json.loads(capsys.readouterr().out)}
    assert set(rows) == {"wskp", "wskp_mr"}
    wskp = rows["wskp"]["presets"]["paper"]
    assert wskp["parameters"] == 38_824
    assert wskp["inference"]["parameters"] == 27_382
    # Convolutions only: 2 x the 5x5 weights of the fused network (bias adds are not counted).
    assert wskp["inference"]["flops_per_pixel"] == 2 * (27_382 - 5 * 14 - 12) == 54_600
    assert wskp["flops_per_pixel"] == 76_440  # 2 x the 35 weights per channel pair, identity BN not counted
    assert "inference" not in rows["wskp_mr"]["presets"]["paper"]

    assert cli.main(["models", *only]) == 0
    text = capsys.readouterr().out
    block = text[text.index("wskp  ("):text.index("wskp_mr  (")]
    assert "38,824 params, 0.0764 MFLOP/pixel, input: pixels, training form" in block
    assert "27,382 params, 0.0546 MFLOP/pixel, inference form (re-parameterised)" in block


def test_no_flops_listing_still_gives_inference_parameters(capsys: pytest.CaptureFixture[str]) -> None:
    """`--no-flops` skips the FLOP count but keeps both parameter counts; only models with a fused
    form get an inference entry."""
    assert cli.main(["models", "--json", "--no-flops", "--preset", "paper3", "--preset", "small"]) == 0
    rows = {r["name"]: r for r in json.loads(capsys.readouterr().out)}
    info = rows["wskp"]["presets"]["paper3"]
    assert info["inference"] == {"parameters": 12_640}
    assert "flops_per_pixel" not in info
    others = [n for n, r in rows.items() for i in r["presets"].values() if "inference" in i and n != "wskp"]
    assert not others, others


def test_unknown_model_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    """A typo in --model names the registered models instead of listing nothing."""
    assert cli.main(["models", "--model", "wskpp", "--no-flops"]) == 2
    err = capsys.readouterr().err
    assert "wskpp" in err and "wskp_mr" in err


def test_unknown_preset_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    """Bug caught: `models --preset bogus` printing every model with no preset rows and exit 0."""
    from mcdenoise.cli.main import main

    assert main(["models", "--preset", "bogus", "--no-flops"]) == 2
    err = capsys.readouterr().err.strip()
    assert "no model has preset(s) bogus" in err and "small" in err and "\n" not in err


def test_default_listing_counts_no_flops_and_shows_shipped_weights(monkeypatch: pytest.MonkeyPatch,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """Bugs caught (issue 18): the default `mcdenoise models` counted FLOPs of every preset (41 s on
    2 cores) and did not say which models have shipped weights (the ones `denoise --model NAME`
    and `eval --models NAME` can use)."""
    import mcdenoise.models.info as info

    def no_counting(*a: object, **k: object) -> float:
        raise AssertionError("FLOPs counted without --flops")

    monkeypatch.setattr(info, "flops_per_pixel", no_counting)
    assert cli.main(["models", "--model", "wskp", "--model", "wskp_mr"]) == 0
    text = capsys.readouterr().out
    assert "small          4,564 params, input: pixels, training form, shipped weights" in text
    assert "shipped weights" not in text[text.index("wskp_mr  ("):text.index("Shipped weights")]
    assert "Shipped weights (usable by name in denoise/eval): " in text and "wskp (small)" in text
    assert "add --flops" in text
    assert cli.main(["models", "--json", "--model", "wskp"]) == 0
    presets = json.loads(capsys.readouterr().out)[0]["presets"]
    assert presets["small"]["shipped_weights"] is True and presets["paper"]["shipped_weights"] is False
    assert "flops_per_pixel" not in presets["paper"]
