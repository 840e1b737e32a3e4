"""docs/RESULTS.md's generated blocks name their inputs, and the inputs come from documented
commands (issue 18 section 2: the built-in-scenes block read ``data/scenes``, which no documented
command created)."""

from __future__ import annotations

import argparse
import re
import shlex
from pathlib import Path

from mcdenoise.cli import eval as eval_cli
from mcdenoise.cli import render as render_cli
from mcdenoise.eval.docblock import read_block
from mcdenoise.render.scene_loading import list_builtin_scenes

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "RESULTS.md"


def _parse(sub: object, cmd: str) -> argparse.Namespace:
    argv = shlex.split(cmd)
    assert argv[0] == "mcdenoise", cmd
    p = argparse.ArgumentParser(exit_on_error=False)
    sub.add_parser(p)  # type: ignore[attr-defined]
    return p.parse_args(argv[2:])


def _section(text: str, heading: str) -> str:
    start = text.index(heading)
    nxt = text.find("\n## ", start + len(heading))
    return text[start:nxt if nxt > 0 else None]


def test_builtin_block_inputs_come_from_documented_render_commands() -> None:
    """Catches issue 18: the built-in-scenes block's command reads data/scenes, which no documented
    command creates. The section must state `mcdenoise render` commands that parse, name built-in
    scenes, write into the block's --data folder, store at least the block's largest --spp with a
    reference, and are as many as the block's images."""
    text = RESULTS.read_text()
    block = read_block(RESULTS, "eval:builtin")
    assert block is not None
    m = re.search(r"^Command: `(mcdenoise eval [^`]+)`", block, re.M)
    assert m, "the block names no eval command"
    ev = _parse(eval_cli, m.group(1))
    assert len(ev.data) == 1
    data = Path(ev.data[0])
    images = int(re.search(r"^(\d+) images? \(", block, re.M).group(1))

    intro = _section(text, "## Shipped weights on the built-in scenes").split("<!-- BEGIN generated:eval:builtin")[0]
    renders = [ln.strip() for ln in intro.splitlines() if ln.strip().startswith("mcdenoise render ")]
    assert len(renders) == images, renders
    builtins = list_builtin_scenes()
    outs = set()
    for cmd in renders:
        r = _parse(render_cli, cmd)
        assert r.scene in builtins, r.scene
        assert r.out.parent == data, (r.out, data)  # one image folder each, in the folder eval reads
        assert r.spp >= max(ev.spp) and r.ref_spp > 0, cmd  # eval takes the first k samples, needs a reference
        assert r.variant != "auto", "state the Mitsuba variant: a GPU host renders other pixels"
        outs.add(r.out)
    assert len(outs) == len(renders)
