"""scripts/gpu_campaign.sh, the recipe of campaign 13, run end to end on the CPU at toy size.

The script is what a lent GPU machine runs blind, with minutes of device time and no second try:
a bug found there costs the campaign. Here it runs with the LLVM variant, ``--device cpu``, two
tiny shards and a short deadline, which exercises everything but CUDA: the shards, the merge, the
runs file, the calibration leg, the resume to a measured step count, and the packing.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
@pytest.mark.render
def test_gpu_campaign_script_renders_trains_resumes_and_packs(tmp_path: Path) -> None:
    """Catches: a runs-file line that the script mis-parses (arguments lost or split), a resume
    refused because the second leg's settings differ from the first's, a step count that ignores
    the calibration, a pack missing a run or its checkpoint (what comes back from the device); and a
    second, RESUME_ONLY call that renders again, loses the first call's shards or restarts its runs."""
    runs = tmp_path / "runs.txt"
    runs.write_text("# toy runs\nlm|--model layer --preset small --model-overrides '{\"autoexposure\": 0.18}'\n"
                    "wk|--model wskp --loss smape\n")
    out = tmp_path / "out"
    env = {**os.environ, "SKIP_SITE": "1", "PY": sys.executable, "VARIANT": "llvm_ad_rgb", "DEVICE": "cpu",
           "SHARDS": "2", "RENDER_S": "150", "DEADLINE": "260", "BATCH": "2", "CROP": "32", "CALIB": "3",
           "WORKERS": "0", "COUNT_D": "2", "COUNT_R": "2", "SPP": "4", "REF_SPP": "32", "SEED_D": "5", "SEED_R": "6", "RUNS": str(runs), "OUT": str(out),
           "DATA_ROOT": str(tmp_path / "data")}
    proc = subprocess.run(["bash", "scripts/gpu_campaign.sh"], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=500)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "runs: lm wk" in proc.stdout
    names = sorted(p.name for p in out.iterdir())
    assert names == ["lm.tgz", "lm_ckpt.tgz", "logs.tgz", "wk.tgz", "wk_ckpt.tgz"], names
    for run in ("lm", "wk"):
        with tarfile.open(out / f"{run}.tgz") as t:
            t.extractall(tmp_path / "x", filter="data")
        lines = (tmp_path / "x" / run / "metrics.csv").read_text().splitlines()
        assert int(lines[-1].split(",")[0]) > 3  # resumed past the 3-step calibration leg
    with tarfile.open(out / "logs.tgz") as t:  # the shards' recipes: campaign 16's settings reach them
        t.extractall(tmp_path / "logs", filter="data")
    ds = json.loads((tmp_path / "logs" / "logs" / "ds" / "det_0" / "dataset.json").read_text())
    assert (ds["ref_spp"], ds["seed"], ds["world"]) == (32, 5, "detailed")
    cfg = (tmp_path / "x" / "lm" / "config.json").read_text()
    assert '"autoexposure": 0.18' in cfg and '"preset": "small"' in cfg

    # A second call on the warm machine (RESUME_ONLY=1): no site, no render, no calibration leg;
    # both runs resume from where the first call stopped, on the same shards.
    first = {run: int((tmp_path / "x" / run / "metrics.csv").read_text().splitlines()[-1].split(",")[0])
             for run in ("lm", "wk")}
    out2 = tmp_path / "out2"
    env2 = {**env, "RESUME_ONLY": "1", "DEADLINE": "80", "OUT": str(out2)}
    proc = subprocess.run(["bash", "scripts/gpu_campaign.sh"], cwd=ROOT, env=env2, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "mitsuba ok" not in proc.stdout and "after 45 s" not in proc.stdout  # nothing rendered again
    assert " in 2 shards" in proc.stdout  # it found the first call's 2 shards
    for run in ("lm", "wk"):
        with tarfile.open(out2 / f"{run}.tgz") as t:
            t.extractall(tmp_path / "y", filter="data")
        last = int((tmp_path / "y" / run / "metrics.csv").read_text().splitlines()[-1].split(",")[0])
        assert last > first[run], (run, first[run], last)  # resumed past the first call's end
