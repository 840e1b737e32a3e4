"""`mcdenoise demo` end to end on a tiny render: the path a new user sees first."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mcdenoise.cli import main as cli

pytestmark = pytest.mark.render


def test_demo_tiny_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "demo"
    rc = cli.main(["demo", "--out", str(out), "--size", "24", "--spp", "2", "--ref-spp", "32"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "not built yet" in text
    summary = json.loads((out / "summary.json").read_text())
    noisy = summary["metrics"]["noisy (2 spp)"]
    assert noisy["relmse"] > 0 and noisy["psnr"] > 5
    # Every registered model consumed the real buffers and returned a finite full-size image.
    assert summary["models"] and all(m["ok"] for m in summary["models"].values())
    assert list(out.glob("noisy_reinhard_ev+0.0.png"))
    # A second run reuses the render instead of rendering again.
    assert cli.main(["demo", "--out", str(out), "--size", "24", "--spp", "2", "--ref-spp", "32"]) == 0
    assert "reusing" in capsys.readouterr().out
