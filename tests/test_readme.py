"""The README's tour: every `mcdenoise ...` line parses with the real command-line parser.

Bug caught: a README that tells users a flag or subcommand that does not exist (renamed flags,
a subcommand that was never built). What the commands do is tested by the command's own tests
(test_denoise_cli, test_render, test_dataset_cli, test_train_run, test_eval) and by `make demo`.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from mcdenoise.cli.main import build_parser

README = Path(__file__).resolve().parents[1] / "README.md"


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
