"""`mcdenoise demo` end to end on a tiny render: the path a new user sees first."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mcdenoise.cli import main as cli
from mcdenoise.eval.ranking import terminal_summary
from mcdenoise.models.weights import shipped

pytestmark = pytest.mark.render

TINY = ["--size", "24", "--spp", "2", "--ref-spp", "32"]


def test_demo_tiny_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Bugs caught: a demo that skips the shipped models or OIDN, writes a report without the
    EXRs/PNGs it promises, reuses a render made with other settings, or re-renders needlessly."""
    out = tmp_path / "demo"
    assert cli.main(["demo", "--out", str(out), *TINY]) == 0
    text = capsys.readouterr().out
    # labels: a `small` preset by its model name, others (combine ens) by their weights file's stem
    names = sorted(s.name if s.preset == "small" else s.weights.stem for s in shipped())
    assert names, "no shipped weights in the package"
    doc = json.loads((out / "report" / "results.json").read_text())
    methods = {m["name"] for m in doc["methods"]}
    assert set(names) <= methods and {"noisy", "oidn-high", "oidn-fast"} <= methods
    for name in ["reference", "noisy", "oidn-high", *names]:
        assert (out / "exr" / f"{name}.exr").is_file(), name
        # the name records tonemap and exposure; "combine-ens" must not count "combine-ens_kpcn"'s
        pngs = [p for p in (out / "png").glob(f"{name}_*.png") if p.stem.rsplit("_", 2)[0] == name]
        assert len(pngs) == 1 and pngs[0].stat().st_size > 100, name
        if name != "reference":
            assert name in text  # the printed table has a row per method
    assert (out / "report" / "index.html").is_file() and "report:" in text
    # Bug caught: the demo printed a table of its own (unranked, other columns) instead of the ranked
    # summary `mcdenoise eval` prints; now both print ranking.terminal_summary of the same results.
    assert terminal_summary(doc) in text and "best relMSE first" in text
    # Same settings: the render is reused; another seed: rendered again, never reused.
    assert cli.main(["demo", "--out", str(out), *TINY]) == 0
    assert "reusing" in capsys.readouterr().out
    assert cli.main(["demo", "--out", str(out), *TINY, "--seed", "3", "--models"]) == 0
    again = capsys.readouterr().out
    assert "reusing" not in again and json.loads((out / "render" / "cornell-dof" / "meta.json").read_text())["seed"] == 3
