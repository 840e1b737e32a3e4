"""The command line: version, help, subcommands that are not built yet, one-line errors."""

from __future__ import annotations

import subprocess
import sys

import pytest

from mcdenoise import __version__
from mcdenoise.cli import main as cli


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"mcdenoise {__version__}"


def test_every_subcommand_has_help() -> None:
    parser = cli.build_parser()
    for name in cli.SUBCOMMANDS:
        with pytest.raises(SystemExit) as e:
            parser.parse_args([name, "--help"])
        assert e.value.code == 0


def test_help_descriptions_are_whole_sentences(capsys: pytest.CaptureFixture[str]) -> None:
    """Bug caught (issue 18): `demo --help` showed only the docstring's first line, cut
    mid-sentence ("... denoise it with the shipped"); every description ends its sentence."""
    parser = cli.build_parser()
    for name in cli.SUBCOMMANDS:
        with pytest.raises(SystemExit):
            parser.parse_args([name, "--help"])
        out = capsys.readouterr().out
        desc = " ".join(out.split("\n\n")[1].split())
        assert desc.endswith((".", ")", "`")), (name, desc)
    with pytest.raises(SystemExit):
        parser.parse_args(["demo", "--help"])
    assert "the HTML comparison." in " ".join(capsys.readouterr().out.split())


def test_not_landed_subcommand_says_so_and_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    landed = set()
    for name in cli.SUBCOMMANDS:
        try:
            __import__(f"mcdenoise.cli.{name}")
            landed.add(name)
        except ModuleNotFoundError:
            pass
    pending = [n for n in cli.SUBCOMMANDS if n not in landed]
    if not pending:
        pytest.skip("every subcommand has landed")
    for name in pending:
        assert cli.main([name]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "not built yet" in err[0], err


def test_console_script_runs() -> None:
    # The installed entry point, as a user calls it.
    out = subprocess.run([sys.executable, "-m", "mcdenoise.cli.main", "--version"],
                         capture_output=True, text=True, check=True)
    assert __version__ in out.stdout


def test_version_does_not_import_torch() -> None:
    # `mcdenoise --version` and `--help` must stay instant: no torch or mitsuba at parser build.
    code = "import sys; from mcdenoise.cli.main import build_parser; build_parser(); " \
           "print('torch' in sys.modules, 'mitsuba' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]


def test_models_listing_json(capsys: pytest.CaptureFixture[str]) -> None:
    import json

    from mcdenoise.models.registry import MODELS

    assert cli.main(["models", "--json", "--preset", "small", "--flops"]) == 0
    rows = {r["name"]: r for r in json.loads(capsys.readouterr().out)}
    assert set(rows) == set(MODELS)
    for r in rows.values():
        info = r["presets"]["small"]
        assert info["parameters"] > 0 and info["flops_per_pixel"] > 0 and info["channels"]
        assert (info["input_kind"] == "samples") == ("flops_spp" in info)
    # Independent check of the FLOP count: DPCN is convolutions at full resolution only, so its
    # FLOPs per pixel are 2 x its convolution weights (parameters minus biases).
    import torch

    from mcdenoise.models.registry import build_model

    dpcn = build_model("dpcn", "small")
    weights = sum(m.weight.numel() for m in dpcn.modules() if isinstance(m, torch.nn.Conv2d))
    assert rows["dpcn"]["presets"]["small"]["flops_per_pixel"] == 2 * weights


def test_precision_defaults_are_explained_in_both_helps(capsys: pytest.CaptureFixture[str]) -> None:
    """Bug caught (issue 18): `eval --precision` defaulted to float32 while `denoise` defaulted to
    auto, and neither help said so; each now names the other's default and why."""
    parser = cli.build_parser()
    helps = {}
    for name in ("eval", "denoise"):
        with pytest.raises(SystemExit):
            parser.parse_args([name, "--help"])
        helps[name] = " ".join(capsys.readouterr().out.split())
    assert "float32 (default, unlike denoise's auto" in helps["eval"]
    assert "eval defaults to float32" in helps["denoise"]


def test_unexpected_errors_are_one_line_unless_debug(monkeypatch, capsys) -> None:
    """Catches issue 22's 'no command prints a traceback without --debug': an exception no command
    translated (a bug) printed a traceback; it is one line now, and --debug still raises it."""
    import pytest

    from mcdenoise.cli import main as cli_main
    from mcdenoise.cli import models as models_cmd

    def boom(args):
        raise ZeroDivisionError("bad arithmetic")

    monkeypatch.setattr(models_cmd, "run", boom)
    assert cli_main.main(["models"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "internal error: ZeroDivisionError: bad arithmetic" in err and "--debug" in err
    with pytest.raises(ZeroDivisionError):
        cli_main.main(["--debug", "models"])
