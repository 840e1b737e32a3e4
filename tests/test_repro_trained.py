"""The trained reproductions (``mcdenoise repro kpcn-vs-dpcn | sbmc-table2 | layer-table2 | wskp-fig9``):
parsers, a tiny run of each, rerun skipping, the docs block, verdict directions, equal parameters,
and ``TrainConfig.model_overrides`` that the ablations train with."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from pathlib import Path

import pytest

from mcdenoise.cli.main import main
from mcdenoise.cli.repro import add_parser
from mcdenoise.eval.docblock import read_block
from mcdenoise.repro import TRAINED, load_experiment
from mcdenoise.repro.common import Experiment, Variant, _parameters, run_experiment
from train_tiny_data import make_tiny_dataset


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_tiny_dataset(tmp_path_factory.mktemp("repro") / "data", size=16)


def _tiny(exp: Experiment) -> Experiment:
    # 16-pixel crops of batch 1 and two validations: seconds per variant on one CPU core.
    return dataclasses.replace(exp, crop=16, batch=1, validations=2)


@pytest.mark.parametrize("name", list(TRAINED))
def test_parser_reads_every_option(name: str) -> None:
    """Catches an experiment missing from the CLI or an option renamed or dropped."""
    p = argparse.ArgumentParser()
    add_parser(p)
    a = p.parse_args([name, "--data", "D", "--steps", "7", "--seed", "3", "--out", "O", "--write-docs", "R.md"])
    assert (a.experiment, a.data, a.steps, a.seed, a.out, a.write_docs) == (name, "D", 7, 3, "O", "R.md")
    d = p.parse_args([name])
    assert (d.data, d.steps, d.seed, d.out, d.write_docs) == (None, None, 0, "runs/repro", None)
    with pytest.raises(SystemExit):
        p.parse_args([name, "--steps", "0"])


@pytest.mark.parametrize("name", list(TRAINED))
def test_tiny_run_writes_every_variant_with_finite_curves(name: str, tiny: Path, tmp_path: Path) -> None:
    """Catches a variant that does not build or train (e.g. an override field the model lacks),
    a curve with no or non-finite validation points, and a result without a verdict or plot."""
    exp = load_experiment(name)
    res = run_experiment(_tiny(exp), data=tiny, steps=2, out=tmp_path, log=lambda s: None)
    assert list(res["variants"]) == [v.key for v in exp.variants]
    for v in res["variants"].values():
        assert [p["step"] for p in v["curve"]] == [1, 2]
        assert all(math.isfinite(p[m]) for p in v["curve"] for m in ("relmse", "smape", "l1", "psnr"))
        assert v["parameters"] > 0
    assert res["verdict"] in ("agrees", "partly", "disagrees", "inconclusive") and res["explanation"]
    assert res["data"]["val_references"] and res["data"]["val_images"] == 1
    saved = json.loads(Path(res["json"]).read_text())
    assert saved["variants"].keys() == res["variants"].keys()
    assert Path(res["plot"]).stat().st_size > 1000


def test_cli_rerun_skips_finished_runs_and_writes_the_docs_block(tiny: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    """Catches a rerun that trains again instead of skipping, and a block written under another
    key (it would overwrite the eval tables) or missing the claim and verdict."""
    from mcdenoise.repro import wskp_fig9

    monkeypatch.setattr(wskp_fig9, "EXPERIMENT", _tiny(wskp_fig9.EXPERIMENT))
    doc = tmp_path / "RESULTS.md"
    doc.write_text("# Results\n\n<!-- BEGIN generated:eval:x -->\nkeep me\n<!-- END generated:eval:x -->\n")
    args = ["repro", "wskp-fig9", "--data", str(tiny), "--steps", "2", "--out", str(tmp_path / "o"), "--write-docs", str(doc)]
    assert main(args) == 0
    first = capsys.readouterr()
    assert "training 2 steps" in first.err and "verdict:" in first.out
    assert main(args) == 0
    assert first.err.count("training 2 steps") == 4 and "training 2 steps" not in capsys.readouterr().err
    block = read_block(doc, "repro:wskp-fig9")
    assert block is not None and "Verdict:" in block and "33.64" in block and "--steps 2" in block
    assert read_block(doc, "eval:x") == "keep me"


def test_sbmc_ablation_parameters_are_equal_within_one_percent() -> None:
    """Table 2 compares at equal parameters: catches a preset change that gives one ablation more
    capacity (the figures are the small presets' counts, pinned)."""
    exp = load_experiment("sbmc-table2")
    counts = {v.key: _parameters(v) for v in exp.variants}
    assert counts == {"sbmc": 88_889, "sbmc_gather": 88_889, "pixel_gather": 89_481, "pixel_splat": 89_481}
    assert max(counts.values()) / min(counts.values()) < 1.01


def test_layer_and_wskp_variants_differ_only_in_their_overrides() -> None:
    """Catches a variant that silently trains the default model (override not applied): layer
    counts and kernel sizes change the partitioner's and the ImportanceNet's last layer only."""
    layer = {v.key: _parameters(v) for v in load_experiment("layer-table2").variants}
    assert layer["l2"] == layer["weighted"]
    assert layer["l1"] < layer["l2"] < layer["l4"] and layer["l4"] - layer["l1"] < 0.01 * layer["l2"]
    wskp = {v.key: _parameters(v) for v in load_experiment("wskp-fig9").variants}
    assert wskp["k3"] == wskp["k5"] == wskp["k7"] < wskp["fused"]


def _result(metric: str, finals: dict[str, float], steps: int = 100) -> dict:
    # relMSE moves with the metric (PSNR's inverse), so a secondary check agrees with the primary.
    return {"metric": metric, "steps": steps,
            "variants": {k: {"label": k, "curve": [{"step": steps, metric: x, "relmse": 1 / x if metric == "psnr" else x}]}
                         for k, x in finals.items()}}


def test_verdicts_read_the_metric_in_the_right_direction() -> None:
    """Catches a judge that treats PSNR as an error (lower = better) or relMSE as a score."""
    from mcdenoise.repro import kpcn_vs_dpcn, layer_table2, sbmc_table2, wskp_fig9

    assert wskp_fig9.judge(_result("psnr", {"fused": 30.0, "k3": 29.0, "k5": 29.5, "k7": 29.9}))[0] == "agrees"
    assert wskp_fig9.judge(_result("psnr", {"fused": 28.0, "k3": 29.0, "k5": 29.5, "k7": 29.9}))[0] == "disagrees"
    split = _result("psnr", {"fused": 30.0, "k3": 29.0, "k5": 29.5, "k7": 29.9})
    split["variants"]["k3"]["curve"][0]["relmse"] = 0.0  # best PSNR, but not the best relMSE
    assert wskp_fig9.judge(split)[0] == "partly"
    paper = {"sbmc": 0.038, "sbmc_gather": 0.051, "pixel_splat": 0.062, "pixel_gather": 0.088}
    assert sbmc_table2.judge(_result("relmse", paper))[0] == "agrees"
    assert sbmc_table2.judge(_result("relmse", {k: 1 / x for k, x in paper.items()}))[0] == "disagrees"
    assert layer_table2.judge(_result("relmse", {"l1": 0.05, "l2": 0.03, "l4": 0.031, "weighted": 0.032}))[0] == "agrees"
    assert layer_table2.judge(_result("relmse", {"l1": 0.05, "l2": 0.03, "l4": 0.02, "weighted": 0.02}))[0] == "disagrees"
    curve = lambda xs: [{"step": 10 * (i + 1), "l1": x} for i, x in enumerate(xs)]  # noqa: E731
    res = {"metric": "l1", "steps": 40, "variants": {"kpcn": {"curve": curve([0.5, 0.2, 0.1, 0.1])},
                                                     "dpcn": {"curve": curve([0.9, 0.6, 0.4, 0.2])}}}
    verdict, text = kpcn_vs_dpcn.judge(res)
    assert verdict == "agrees" and "by step 20 of 40, 2.0-4.0x sooner" in text
    res["variants"]["kpcn"], res["variants"]["dpcn"] = res["variants"]["dpcn"], res["variants"]["kpcn"]
    assert kpcn_vs_dpcn.judge(res)[0] == "disagrees"


def test_layer_verdict_weighs_gaps_against_the_runs_spread() -> None:
    """Catches issue 18: layer-table2 said "disagrees" when four layers beat two by more than a 2%
    margin although the runs wobbled by 11% over their last validations; a gap within that spread
    is "inconclusive", and one beyond it still disagrees."""
    from mcdenoise.repro import layer_table2

    def res(last3: dict[str, list[float]]) -> dict:
        return {"metric": "relmse", "steps": 300, "variants": {
            k: {"label": k, "curve": [{"step": 100 * (i + 1), "relmse": x} for i, x in enumerate(xs)]}
            for k, xs in last3.items()}}

    # Two layers wobble by 12% (0.0191 -> 0.0170); four beat two by 5%, weighted by 4%: within it.
    noisy = res({"l1": [0.03, 0.03, 0.03], "l2": [0.0191, 0.0189, 0.0170], "l4": [0.0165, 0.0166, 0.01615],
                 "weighted": [0.0165, 0.0164, 0.01632]})
    verdict, text = layer_table2.judge(noisy)
    assert verdict == "inconclusive", text
    assert "noise 12.4% of L=2" in text
    # The same gaps with steady runs are beyond the noise: the claims are contradicted.
    steady = res({"l1": [0.03] * 3, "l2": [0.017] * 3, "l4": [0.01615] * 3, "weighted": [0.01632] * 3})
    assert layer_table2.judge(steady)[0] == "disagrees"
    # docs/RESULTS.md's run: four beat two by 22%, weighted beats alpha by 35%, spread 11%.
    docs = res({"l1": [0.01652, 0.02311, 0.02262], "l2": [0.01911, 0.01888, 0.01715],
                "l4": [0.01204, 0.01349, 0.0134], "weighted": [0.01069, 0.01148, 0.0111]})
    assert layer_table2.judge(docs)[0] == "disagrees"


def test_kpcn_speed_up_at_the_first_validation_point_is_a_lower_bound() -> None:
    """Catches issue 18: "8.0x sooner" stated as a measurement when KPCN was already below DPCN's
    final error at the first validation point (step 188 of 1500), which only bounds it from below."""
    from mcdenoise.repro import kpcn_vs_dpcn

    curve = lambda xs: [{"step": 188 * (i + 1), "l1": x} for i, x in enumerate(xs)]  # noqa: E731
    res = {"metric": "l1", "steps": 1504, "variants": {"kpcn": {"curve": curve([0.0188, 0.0183, 0.0173])},
                                                       "dpcn": {"curve": curve([0.047, 0.034, 0.0255])}}}
    verdict, text = kpcn_vs_dpcn.judge(res)
    assert verdict == "agrees" and "at least 8.0x sooner" in text and "lower bound" in text and "first validation" in text


def test_model_overrides_reach_the_model_and_the_run_folder(tiny: Path, tmp_path: Path) -> None:
    """Catches overrides ignored by the engine (the ablation would train the preset), tuples that
    break an exact resume (JSON reads them back as lists), a typo'd field accepted silently, and
    run folders from before the field existed refused on resume."""
    from mcdenoise.train.config import ConfigError, TrainConfig
    from mcdenoise.train.loop import train

    cfg = TrainConfig(model="wskp", model_overrides={"kernel_sizes": (5,)}, data=str(tiny), steps=2, batch=1, crop=16,
                      workers=0, progress=False, val_every=0)
    assert cfg.to_json()["model_overrides"] == {"kernel_sizes": [5]}
    train(cfg, tmp_path / "run")
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["model_config"]["kernel_sizes"] == [5] and saved["train"]["model_overrides"] == {"kernel_sizes": [5]}
    # The final weights file alone rebuilds the overridden architecture (it failed to load by path).
    from mcdenoise.models.weights import load_denoiser

    assert list(load_denoiser(tmp_path / "run" / "model.safetensors")[0].config.kernel_sizes) == [5]
    assert train(cfg, tmp_path / "run", resume=True).step == 2  # same settings: accepted, nothing to do
    # A run folder written before the field existed still resumes under a command without overrides.
    plain = dataclasses.replace(cfg, model_overrides={})
    train(plain, tmp_path / "old")
    doc = json.loads((tmp_path / "old" / "config.json").read_text())
    del doc["train"]["model_overrides"]
    (tmp_path / "old" / "config.json").write_text(json.dumps(doc))
    assert train(plain, tmp_path / "old", resume=True).step == 2
    with pytest.raises(ConfigError, match="kernel_sizez"):
        train(dataclasses.replace(cfg, model_overrides={"kernel_sizez": (5,)}), tmp_path / "typo")


def test_every_variant_names_a_registered_model_and_known_fields() -> None:
    """Catches a variant spec that would only fail after the variants before it trained for minutes."""
    from mcdenoise.models.registry import MODELS, _load_all

    _load_all()
    for name in TRAINED:
        for v in load_experiment(name).variants:
            assert isinstance(v, Variant) and v.model in MODELS
            fields = {f.name for f in dataclasses.fields(MODELS[v.model].config("small"))}
            assert set(dict(v.overrides)) <= fields


@pytest.mark.slow
def test_without_data_renders_the_cache_once_and_reuses_it(tmp_path: Path, monkeypatch) -> None:
    """Catches the fresh-clone path broken (the command must render its own held-out data with
    references when no --data is given) and a rerun that renders the cache again."""
    from mcdenoise.repro import common, wskp_fig9

    monkeypatch.setattr(common, "CACHE_DATASET", dict(count=2, seed=10, spp=4, ref_spp=16, width=16, height=16, views=1,
                                                      objects=(3, 5), fractions=(0.5, 0.5, 0.0)))
    exp = _tiny(wskp_fig9.EXPERIMENT)
    res = run_experiment(exp, steps=1, out=tmp_path, log=lambda s: None)
    assert res["default_data"] and res["data"]["val_references"] and res["data"]["val_images"] == 1
    manifest = tmp_path / "data" / "manifest.json"
    before = manifest.stat().st_mtime_ns
    lines: list[str] = []
    run_experiment(dataclasses.replace(exp, name="wskp-again"), steps=1, out=tmp_path, log=lines.append)
    assert manifest.stat().st_mtime_ns == before and not any("rendering" in s for s in lines)


def test_data_without_references_is_one_line_naming_the_fix(tmp_path: Path, capsys) -> None:
    """Bug caught (issue 18): README's training data (`dataset --ref-spp 0`) given to `repro
    --data` failed inside the sampler with a bare ValueError (`no reference.exr to train
    against`, a traceback); it must be one line naming the folder, the cause and the fix, before
    any training starts."""
    from mcdenoise.data.dataset import read_manifest
    from mcdenoise.data.meta import seal_meta

    data = make_tiny_dataset(tmp_path / "noref", size=16)
    for e in read_manifest(data)[:2]:
        img = data / e["path"]
        meta = json.loads((img / "meta.json").read_text())
        del meta["files"]["reference"]
        (img / "meta.json").write_text(json.dumps(seal_meta(meta)))  # as a --ref-spp 0 render writes it
        (img / "reference.exr").unlink()
    assert main(["repro", "kpcn-vs-dpcn", "--data", str(data), "--steps", "1", "--out", str(tmp_path / "o"),
                 "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"{data}: 2 of 4 train/val images have no reference.exr" in err
    assert "--ref-spp 64 or more" in err and "leave out --data" in err
    assert not (tmp_path / "o" / "kpcn-vs-dpcn").exists()  # refused before any run folder
