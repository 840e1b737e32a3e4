"""The README's tour: every `mcdenoise ...` line parses with the real command-line parser, and
`test_readme_tour_runs` runs them all, in order, in one temporary folder, at tiny sizes (the TINY
table below names every flag it shrinks; nothing else changes).

Bugs caught: a README that tells users a flag or subcommand that does not exist (renamed flags,
a subcommand that was never built), and a tour whose commands parse but fail or do not leave the
files the next command reads. What each command does in detail is tested by its own tests
(test_denoise_cli, test_render, test_dataset_cli, test_train_run, test_eval) and by `make demo`.
"""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mcdenoise.cli.main import build_parser

README = Path(__file__).resolve().parents[1] / "README.md"
SCENES = Path(__file__).parent / "fixtures" / "scenes"


def _commands() -> list[str]:
    text = README.read_text()
    blocks = re.findall(r"```sh\n(.*?)```", text, flags=re.S)
    lines = [ln.split("#", 1)[0].strip() for b in blocks for ln in b.splitlines()]
    return [ln for ln in lines if ln.startswith("mcdenoise ")]


def test_readme_has_the_tour() -> None:
    cmds = " ".join(_commands())
    for sub in ("denoise", "render", "dataset", "train", "eval"):
        assert f"mcdenoise {sub} " in cmds, sub


@pytest.mark.parametrize("cmd", _commands())
def test_readme_command_parses(cmd: str) -> None:
    argv = shlex.split(cmd)[1:]
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:  # argparse exits on an unknown flag or subcommand
        if e.code not in (0, None):
            pytest.fail(f"README command does not parse: {cmd}")
        return
    assert args.command == argv[0]


# ----------------------------------------------------------------------------- the tour, run

#: How the tour test shrinks the README's commands. Each key is the start of one README command;
#: its flags are set to these values (replaced where the README gives the flag, appended where it
#: does not). Only size, count, sample and step flags appear here: every other flag, the
#: subcommands and their order are the README's own. A key that matches no README command fails
#: the test, so the table cannot drift from the README unnoticed.
TINY: dict[str, dict[str, str]] = {
    "mcdenoise render cornell-dof": {"--spp": "2", "--size": "16"},
    "mcdenoise render my_scene.xml": {"--spp": "2"},  # the test's my_scene.xml is 16x16
    "mcdenoise dataset --out data/train": {"--count": "2", "--spp": "2", "--size": "16"},
    "mcdenoise train --model layer": {"--steps": "2", "--batch": "2", "--crop": "16"},
    "mcdenoise dataset --out data/test": {"--count": "1", "--ref-spp": "32", "--size": "24"},
}

#: Files each command must leave for the commands after it (or for the user, at the end).
PRODUCES: dict[str, list[str]] = {
    "mcdenoise denoise render.exr": ["clean.exr", "clean.png"],
    "mcdenoise render cornell-dof": ["renders/dof/meta.json", "renders/dof/samples.bin"],
    "mcdenoise render my_scene.xml": ["renders/mine/meta.json", "renders/mine/samples.bin"],
    "mcdenoise denoise renders/dof": ["dof.exr"],
    "mcdenoise dataset --out data/train": ["data/train/dataset.json", "data/train/manifest.json"],
    "mcdenoise train --model layer": ["runs/layer/config.json", "runs/layer/model.safetensors"],
    "mcdenoise dataset --out data/test": ["data/test/dataset.json", "data/test/manifest.json"],
    "mcdenoise eval": ["reports/test/index.html", "reports/test/results.json", "reports/test/results.csv"],
}


def _tiny(cmd: str) -> list[str]:
    """The README command `cmd` as argv, with TINY's values substituted."""
    argv = shlex.split(cmd)
    for key, flags in TINY.items():
        if cmd.startswith(key):
            for flag, value in flags.items():
                if flag in argv:
                    argv[argv.index(flag) + 1] = value
                else:
                    argv += [flag, value]
    return argv


def _user_inputs(folder: Path) -> None:
    """What the tour assumes the user has: a Blender render and a Mitsuba scene file."""
    from mcdenoise.io.exr import write_exr_raw

    rng = np.random.default_rng(0)
    h, w = 16, 20
    ch = {}
    for c in "RGB":  # Cycles' names with Denoising Data enabled
        ch[f"ViewLayer.Noisy Image.{c}"] = (rng.random((h, w)) * 2).astype(np.float32)
        ch[f"ViewLayer.Denoising Albedo.{c}"] = rng.random((h, w)).astype(np.float32)
    for c in "XYZ":
        ch[f"ViewLayer.Denoising Normal.{c}"] = (rng.random((h, w)) * 2 - 1).astype(np.float32)
    ch["ViewLayer.Denoising Depth.Z"] = (rng.random((h, w)) * 5).astype(np.float32)
    write_exr_raw(folder / "render.exr", ch)
    xml = (SCENES / "thinlens_textured.xml").read_text()
    (folder / "my_scene.xml").write_text(xml.replace('name="res" value="64"', 'name="res" value="16"'))


def test_tiny_table_matches_the_readme() -> None:
    """Bug caught: a substitution for a command the README no longer has (the tour test would then
    silently run the full-size command or skip the shrinking it documents)."""
    cmds = _commands()
    for key in [*TINY, *PRODUCES]:
        assert sum(c.startswith(key) for c in cmds) == 1, f"{key!r} matches no single README command"
    assert _tiny("mcdenoise train --model layer --out r --steps 9")[-6:] == ["--steps", "2", "--batch", "2", "--crop", "16"]


@pytest.mark.render
def test_readme_tour_runs(tmp_path: Path) -> None:
    """Every `mcdenoise` line of README's sh blocks, in README order, as the installed command in one
    folder, at the sizes of TINY. Bug caught: README's claim that its tour is run by a test was false
    (the test only parsed the lines), so a command that parses but fails (e.g. a dataset that
    `train` cannot read, a run folder `--resume` or `eval` refuses, a scene file that does not
    render) went unnoticed."""
    exe = Path(sys.executable).with_name("mcdenoise")
    assert exe.is_file(), f"no installed `mcdenoise` next to {sys.executable}"
    _user_inputs(tmp_path)
    cmds = _commands()
    assert [c.split()[1] for c in cmds][:2] == ["denoise", "render"]
    for cmd in cmds:
        argv = _tiny(cmd)
        r = subprocess.run([str(exe), *argv[1:]], cwd=tmp_path, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, f"{' '.join(argv)} exited {r.returncode}:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"
        for key, paths in PRODUCES.items():
            if cmd.startswith(key):
                missing = [p for p in paths if not (tmp_path / p).is_file()]
                assert not missing, f"{cmd}: did not write {missing}"
        if cmd.startswith("mcdenoise train --out runs/layer --resume"):
            assert "already trained for 2 steps" in r.stdout + r.stderr
        if cmd.startswith("mcdenoise eval"):
            assert "best relMSE first" in r.stdout  # the ranked summary reaches the terminal


def test_readme_python_snippet_runs() -> None:
    """The tour's Python lines, run as written on small arrays. Bug caught: a snippet whose call
    signature drifted from `mcdenoise.denoise` (it was never run)."""
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks
    rng = np.random.default_rng(0)
    for code in blocks:
        ns = {name: rng.random((16, 20, 3), dtype=np.float32) for name in ("color", "albedo", "normal")}
        ns["depth"] = rng.random((16, 20, 1), dtype=np.float32)
        exec(compile(code, "README.md", "exec"), ns)
        assert ns["clean"].shape == (16, 20, 3)


def test_readme_names_the_test_that_runs_its_tour() -> None:
    """Bug caught: README said every tour command 'is run by a test' while the test only parsed
    them; the claim must name the test that runs them, and that test must exist."""
    text = " ".join(README.read_text().split())
    assert "tests/test_readme.py::test_readme_tour_runs" in text
    assert "test_readme_tour_runs" in globals()


# ----------------------------------------------------------------------------- speed figures

DOCS_WITH_SPEED = [README, README.parent / "docs" / "DENOISE.md"]
#: A time or a speed ratio: "214 s", "9 s", "606 ms", "16-43 CPU-minutes", "0.676x", "ms/MP".
_SPEED = re.compile(r"\b\d+(?:\.\d+)? ?(?:s|ms|min|minutes|CPU-minutes)\b|\b\d+(?:\.\d+)?x\b|\bms/MP\b")
_CPU = re.compile(r"EPYC|Xeon|not recorded|do not record|did not record|GPU")
_PRECISION = re.compile(r"float32|bfloat16|precision")


def _speed_paragraphs(text: str) -> list[str]:
    """Paragraphs and list items (joined to one line) with a time or speed ratio; each line of a
    code block counts on its own."""
    code = [ln for b in re.findall(r"```[a-z]*\n(.*?)```", text, flags=re.S) for ln in b.splitlines()]
    prose = re.sub(r"```.*?```", "", text, flags=re.S)
    items = [it for block in re.split(r"\n\s*\n", prose) for it in re.split(r"\n(?=[-*] )", block)]
    return [p for p in (" ".join(x.split()) for x in [*items, *code]) if _SPEED.search(p)]


@pytest.mark.parametrize("doc", DOCS_WITH_SPEED, ids=lambda p: p.name)
def test_speed_figures_name_cpu_precision_and_threads(doc: Path) -> None:
    """Bug caught: speed figures that said only '2-core CPU' or 'on 2 cores' (the 4K denoise times
    in DENOISE.md, the demo's and make test's durations, the render-speed ratio in README) and so
    could not be compared across machines (issue 18 section 2). A paragraph or list item with a
    time or a speed ratio must name the CPU model (or say it was not recorded), the precision and
    the thread count."""
    bad = []
    for para in _speed_paragraphs(doc.read_text()):
        missing = [what for what, rx in (("CPU model", _CPU), ("precision", _PRECISION), ("threads", re.compile("thread")))
                   if not rx.search(para)]
        if missing:
            bad.append(f"{', '.join(missing)} missing: {para[:160]}")
    assert not bad, "\n".join(bad)
