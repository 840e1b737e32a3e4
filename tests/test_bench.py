"""mcdenoise bench: interleaved timing, per-call peak memory, the time budget, ratios/targets,
and the command on a reduced set (the full ``--quick`` is a slow test)."""

from __future__ import annotations

import json

import pytest
import torch

from mcdenoise.bench.memory import cpu_peak_supported, peak_call_memory
from mcdenoise.bench.plan import BenchConfig, parse_method, priority, quick_config
from mcdenoise.bench.report import api_rows, markdown, ratios, target_rows
from mcdenoise.bench.timing import interleaved_times
from mcdenoise.cli.main import main
from mcdenoise.eval.oidn import oidn_available

needs_oidn = pytest.mark.skipif(not oidn_available(), reason="pyoidn (OIDN 2.5.1) not installed")


def test_interleaved_times_round_robin() -> None:
    """Bug caught: methods timed in blocks (all rounds of A, then of B), so a burst of background
    load lands on one method only; the call order must be A B A B."""
    order: list[str] = []
    out = interleaved_times({"a": lambda: order.append("a"), "b": lambda: order.append("b")}, 3)
    assert order == ["a", "b"] * 3
    assert {k: len(v) for k, v in out.items()} == {"a": 3, "b": 3}


def test_interleaved_times_caps_slow_entries_to_the_first_rounds() -> None:
    """Bug caught: a slow entry capped to one round timed after the others (out of their
    rounds, so background load would hit it alone) or dropping the others' rounds."""
    order: list[str] = []
    out = interleaved_times({"a": lambda: order.append("a"), "b": lambda: order.append("b")}, 3, max_rounds={"b": 1})
    assert order == ["a", "b", "a", "a"]
    assert {k: len(v) for k, v in out.items()} == {"a": 3, "b": 1}


@pytest.mark.skipif(not cpu_peak_supported(), reason="needs Linux /proc/self/clear_refs")
def test_peak_memory_is_per_call_and_sees_torch() -> None:
    """Bugs caught: a Python-heap measure (tracemalloc sees 0 of a torch tensor), and a
    process-wide peak (ru_maxrss) that reports the earlier large call again for a small one."""
    mib = 2**20

    def big() -> None:
        x = torch.empty(96 * mib // 4)
        x.fill_(1.0)  # touch every page: RSS counts touched pages only
        del x

    _, first = peak_call_memory(big)
    assert first is not None and 88 * mib < first < 140 * mib, first
    _, small = peak_call_memory(lambda: torch.ones(mib // 4).sum())
    assert small is not None and small < 40 * mib, small


def test_parse_method_and_priority() -> None:
    """Bug caught: a target entry (kept whatever the budget) demoted, or OIDN dropped for time."""
    assert parse_method("wskp").label == "wskp:small" and parse_method("oidn").label == "oidn:high"
    assert priority(parse_method("oidn:fast"), None) == 0
    assert priority(parse_method("sbmc:small"), 8) == 0 and priority(parse_method("sbmc:small"), 32) == 2
    assert priority(parse_method("wskp:paper"), None) == 0 and priority(parse_method("dpcn"), None) == 1
    # Targets are kept at the target size only; WSKP's paper presets also at the paper's 720p.
    assert priority(parse_method("sbmc:small"), 8, (1280, 720)) == 1
    assert priority(parse_method("sbmc:small"), 8, (1920, 1080)) == 0
    assert priority(parse_method("wskp:paper3"), None, (1280, 720)) == 0


def _fake_result() -> dict:
    e = lambda m, s, t: {"method": m, "width": 1920, "height": 1080, "spp": s, "status": "ok", "median_s": t,
                         "times_s": [t], "peak_bytes": 2**20}
    return {"machine": {"date": "d", "cpu": "c", "cores": 2, "torch": "t", "torch_threads": 2, "oidn": "2.5.1",
                        "device": "cpu"},
            "config": {"sizes": [[1920, 1080]], "spp": [1, 8], "warmup": 1, "rounds": 3, "fast": True, "device": "cpu",
                       "methods": ["oidn:high", "oidn:fast", "wskp:paper", "sbmc:small"], "train": {}},
            "memory_method": "m", "peak_conv": {"channels": 8, "side": 8, "gflops": 10.0}, "parameters": {},
            "entries": [e("oidn:high", None, 3.0), e("oidn:fast", None, 1.5), e("wskp:paper", None, 0.6),
                        e("sbmc:small", 8, 45.0), e("sbmc:small", 1, 9.0)],
            "training": [], "wall_s": 1.0}


def test_ratios_and_targets() -> None:
    """Bug caught: ratios taken against the wrong OIDN quality or size, a target marked met
    above its limit, or a target silently dropped when its model was not measured."""
    res = _fake_result()
    assert ratios(res, res["entries"][2]) == {"high": pytest.approx(0.2), "fast": pytest.approx(0.4)}
    rows = {r["method"]: r for r in target_rows(res)}
    assert rows["wskp:paper"]["met"] and rows["wskp:paper"]["ratio"] == pytest.approx(0.2)
    assert not rows["sbmc:small"]["met"] and rows["sbmc:small"]["ratio"] == pytest.approx(15.0)
    assert "kpcn:small" not in rows  # not asked for: no row
    text = markdown(res)
    assert "| sbmc:small | 8 | <= 10x | 15 |" in text
    assert "| sbmc:small | 1920x1080 | 1.00 | 5.00 |" in text  # spp scaling relative to 1 spp


@needs_oidn
def test_run_bench_reduced_set_and_budget() -> None:
    """Bugs caught: entries missing or unpaired with OIDN, JSON that does not serialise, and a
    budget that is ignored (with 0 s left for the second size, only OIDN and targets run)."""
    from mcdenoise.bench.run import run_bench

    methods = [parse_method(t) for t in ("oidn:high", "oidn:fast", "wskp:small", "layer_optimized:small")]
    cfg = BenchConfig(methods=methods, sizes=((24, 24), (40, 32)), spp=(1, 8), rounds=1, budget_s=0.0,
                      train_batch=2, train_crop=16, train_steps=1, peak_conv=(8, 32), target_size=(40, 32))
    res = run_bench(cfg, log=lambda _: None)
    json.dumps(res)
    ok = {(e["method"], e["width"], e["spp"]) for e in res["entries"] if e["status"] == "ok"}
    assert {("oidn:high", 24, None), ("wskp:small", 24, None), ("layer_optimized:small", 24, 1),
            ("layer_optimized:small", 24, 8)} <= ok
    assert ("oidn:high", 40, None) in ok and ("layer_optimized:small", 40, 8) in ok  # a target: kept
    skipped = {(e["method"], e["spp"]) for e in res["entries"] if e["status"] == "skipped" and e["width"] == 40}
    assert skipped == {("wskp:small", None), ("wskp:small api", None), ("layer_optimized:small", 1)}
    assert all(e["flops_per_pixel"] > 0 for e in res["entries"] if e["status"] == "ok" and e["method"] != "oidn:high"
               and not e["method"].startswith("oidn") and not e["method"].endswith(" api"))
    assert {t["method"] for t in res["training"]} == {"wskp:small", "layer_optimized:small"}
    assert all(t["crops_per_s"] > 0 for t in res["training"])
    assert res["peak_conv"]["gflops"] > 0
    # slow_s = 0: every entry after the first size is "slow" and gets one round, the first size all.
    cfg.rounds, cfg.slow_s, cfg.train_steps = 2, 0.0, 0
    res = run_bench(cfg, log=lambda _: None)
    n = {(e["method"], e["width"]): len(e["times_s"]) for e in res["entries"] if e["status"] == "ok"}
    assert n[("oidn:high", 24)] == 2 and n[("oidn:high", 40)] == 1


@needs_oidn
def test_cli_bench_json_out(tmp_path, capsys) -> None:
    """Bug caught: the command's flags not reaching the run (sizes, models, rounds) or --out not
    written; an unknown model must be a one-line error, not a traceback."""
    out = tmp_path / "b.json"
    rc = main(["bench", "--quick", "--models", "wskp", "--sizes", "24x16", "--spp", "1", "--rounds", "1",
               "--train-steps", "0", "--json", "--out", str(out)])
    assert rc == 0
    printed = json.loads(capsys.readouterr().out)
    saved = json.loads(out.read_text())
    assert printed["config"]["methods"] == saved["config"]["methods"] == ["oidn:high", "oidn:fast", "wskp:small",
                                                                           "wskp:small api"]
    assert {(e["width"], e["height"]) for e in saved["entries"]} == {(24, 16)}
    assert main(["bench", "--models", "nosuchmodel"]) == 1
    assert "unknown model" in capsys.readouterr().err


@needs_oidn
def test_quick_bench_runs(tmp_path) -> None:
    """Bug caught: `--quick` failing on the real target models (CI runs it: ~10 s). Its size is
    bounded by the work it is configured to do (test_quick_config_is_small), not by a wall-clock
    limit that a slow or loaded CPU could miss (issue 18)."""
    assert main(["bench", "--quick", "--out", str(tmp_path / "q.md")]) == 0
    assert "### 256x256" in (tmp_path / "q.md").read_text()


def test_quick_config_is_small() -> None:
    """Bug caught: quick inheriting the full run's sizes or spp list (then it is not quick)."""
    q = quick_config()
    assert q.sizes == ((256, 256),) and q.spp == (1, 8) and q.rounds <= 2
    assert len(q.methods) <= 8 and q.train_steps <= 2 and q.warmup <= 1


def test_from_json_rerenders_docs_block(tmp_path, capsys) -> None:
    """Bug caught: a saved run that cannot be turned back into the tables (a crash after
    measuring would lose 15 minutes), or a docs update that overwrites the prose around the block."""
    saved = tmp_path / "r.json"
    saved.write_text(json.dumps({**_fake_result(), "command": "mcdenoise bench"}))
    doc = tmp_path / "PERF.md"
    doc.write_text("# Perf\n\nprose before\n\n<!-- BEGIN generated:bench:cpu -->\nOLDBLOCK\n<!-- END generated:bench:cpu -->\n\nprose after\n")
    assert main(["bench", "--from-json", str(saved), "--docs", str(doc)]) == 0
    text = doc.read_text()
    assert "prose before" in text and "prose after" in text and "OLDBLOCK" not in text
    assert "| wskp:paper | - | <= 0.25x | 0.2 |" in text and "Command: `mcdenoise bench`" in text
    assert "### 1920x1080" in capsys.readouterr().out


def test_unmeasured_target_is_not_reported_as_failed() -> None:
    """Bug caught (issue 18): `bench --quick` times 256x256 only, and its targets at 1920x1080
    were printed ``not measured | **no**``, i.e. as failures; a target never timed is neither met
    nor missed."""
    res = _fake_result()
    res["config"]["methods"].append("kpcn:small")  # asked for, never timed at 1920x1080
    rows = {r["method"]: r for r in target_rows(res)}
    assert rows["kpcn:small"]["met"] is None and rows["kpcn:small"]["ratio"] is None
    assert rows["sbmc:small"]["met"] is False
    line = next(ln for ln in markdown(res).splitlines() if ln.startswith("| kpcn:small | - | <= 1x"))
    assert line.endswith("| not measured | - | not measured |") and "**no**" not in line, line


def test_overloaded_machine_is_warned_about() -> None:
    """Bug caught (issue 18): timings taken while the 1-minute load average exceeded the cores
    (a render in the background) were printed without a word; the report, and the log, warn."""
    from mcdenoise.bench.timing import busy_warning, usable_cores

    n = usable_cores()
    assert busy_warning(load=float(n)) is None
    w = busy_warning("at start", load=n + 1.5)
    assert w is not None and f"load average {n + 1.5:.2f} at start exceeds the {n} usable core(s)" in w
    res = _fake_result()
    res["machine"].update({"load_start": 0.5, "load_end": 0.7, "oidn_threads": 1})
    text = markdown(res)
    assert "**Warning**" not in text and "OIDN 2.5.1 (1 threads)" in text
    res["machine"]["load_end"] = 3.9
    assert "**Warning**: load average 3.9 at end exceeded the 2 cores" in markdown(res)


@needs_oidn
def test_bench_times_the_public_api_beside_the_model_call() -> None:
    """Catches issue 18: `bench` timed only the bare model call, so the public API's extra cost
    (0.42x against 0.24x OIDN high for shipped wskp at 1080p) was invisible. Every model with shipped
    weights, pixel and sample models alike, gets a `NAME:PRESET api` entry in the same rounds (a
    model without shipped weights none), and the report sets the two side by side."""
    from mcdenoise.bench.run import _Runner, run_bench

    methods = [parse_method(t) for t in ("oidn:high", "wskp:small", "kpcn:small", "sbmc:small", "layer_optimized:small")]
    cfg = BenchConfig(methods=methods, sizes=((24, 16),), spp=(2,), rounds=1, warmup=1, train_steps=0, peak_conv=(8, 32))
    res = run_bench(cfg, log=lambda _: None)
    bad = [e for e in res["entries"] if e["status"] != "ok"]
    assert not bad, bad
    ok = {(e["method"], e["spp"]) for e in res["entries"]}
    assert {("wskp:small api", None), ("kpcn:small api", None), ("sbmc:small api", 2)} <= ok
    assert not any(m.startswith("layer_optimized") and m.endswith(" api") for m, _ in ok)
    rows = {r["method"]: r for r in api_rows(res)}
    assert set(rows) == {"wskp:small", "kpcn:small", "sbmc:small"}
    assert all(r["api_s"] > 0 and r["model_s"] > 0 for r in rows.values())
    assert "### Public API against the bare model call" in markdown(res)
    cfg.api = False
    assert not any(m.api for m in _Runner(cfg, print).methods)


def test_api_rows_flag_an_api_slower_than_the_model_by_over_ten_percent() -> None:
    """Catches a report that pairs the API entry with the wrong row or hides a slow API path."""
    def e(method: str, s: float, spp: int | None = None) -> dict:
        return {"method": method, "width": 64, "height": 64, "spp": spp, "status": "ok", "median_s": s}

    res = {"entries": [e("wskp:small", 1.0), e("wskp:small api", 1.05), e("sbmc:small", 2.0, 8),
                       e("sbmc:small api", 3.0, 8), e("sbmc:small api", 9.0, 4)]}
    rows = {r["method"]: r for r in api_rows(res)}
    assert rows["wskp:small"]["within"] and abs(rows["wskp:small"]["ratio"] - 1.05) < 1e-9
    assert not rows["sbmc:small"]["within"] and rows["sbmc:small"]["spp"] == 8 and len(api_rows(res)) == 2


@needs_oidn
def test_cli_no_api_leaves_the_api_entries_out(capsys) -> None:
    """Catches `--no-api` not reaching the run (the API entries double a shipped model's cost)."""
    assert main(["bench", "--models", "wskp", "--sizes", "16x16", "--spp", "1", "--rounds", "1", "--train-steps", "0",
                 "--no-api", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["config"]["methods"] == ["oidn:high", "oidn:fast", "wskp:small"]


def test_whole_path_of_a_combiner_counts_every_oidn_run_it_needs() -> None:
    """Bug caught (issue 20): the prefiltered combiner's whole path was reported as its own time
    plus OIDN high, leaving out the prefiltered OIDN run that is also its input (about 2x OIDN)."""
    res = _fake_result()
    e = lambda m, t: {"method": m, "width": 1920, "height": 1080, "spp": None, "status": "ok", "median_s": t,
                      "times_s": [t], "peak_bytes": 2**20}
    res["entries"] += [e("combine:small", 1.0), e("combine:ens", 1.2), e("combine:ens_kpcn", 5.0), e("combine:kpcn", 5.0)]
    text = markdown(res)
    assert "combine:small 4,000 (1.33x OIDN high; with oidn:high)" in text
    assert "combine:ens not measured (needs oidn:high and oidn:high-pf)" in text
    # every preset with the prefiltered candidate, not a list of names (campaign 10's ens_kpcn was missed)
    assert "combine:ens_kpcn not measured (needs oidn:high and oidn:high-pf)" in text
    assert "combine:kpcn 8,000 (2.67x OIDN high; with oidn:high)" in text
    res["entries"].append(e("oidn:high-pf", 6.0))
    text = markdown(res)
    assert "(3.4x OIDN high; with oidn:high + oidn:high-pf)" in text
    # its API row (given the candidates like the bare call) needs the same runs: it said 1.32x
    res["entries"].append(e("combine:ens api", 1.3))
    assert "combine:ens api 10,300 (3.43x OIDN high; with oidn:high + oidn:high-pf)" in markdown(res)


def test_interleaved_times_settles_after_a_switch_of_library() -> None:
    """Bug caught (issue 18): the model timed right after OIDN in each round paid a first-call
    penalty (1.8x) that the others did not; after a switch of group the call is made once untimed."""
    order: list[str] = []
    fns = {n: (lambda n=n: order.append(n)) for n in ("oidn", "a", "b")}
    out = interleaved_times(fns, 2, groups={"oidn": "oidn", "a": "torch", "b": "torch"})
    assert order == ["oidn", "a", "a", "b", "oidn", "oidn", "a", "a", "b"]
    assert all(len(v) == 2 for v in out.values())
