"""The ``mcdenoise`` command: one subcommand per pipeline stage.

Each subcommand lives in ``mcdenoise/cli/<name>.py`` and exposes ``add_parser(subparsers)`` and
``run(args) -> int``. A subcommand whose issue has not landed says so and exits 2.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from mcdenoise import __version__
from mcdenoise.errors import McDenoiseError

#: name -> one-line help. Order is the pipeline's.
SUBCOMMANDS: dict[str, str] = {
    "render": "render per-sample buffers and a reference from a Mitsuba 3 scene",
    "dataset": "render a procedural training dataset with a scene-level split",
    "train": "train a denoiser",
    "eval": "evaluate denoisers and the OIDN baseline, write a report",
    "denoise": "denoise an image folder or EXR",
    "export": "export a denoiser to ONNX or TorchScript",
    "models": "list the registered denoisers",
    "bench": "measure speed",
    "repro": "reproduce paper experiments",
    "demo": "run the main job end to end on a built-in default",
}


class NotLanded(Exception):
    """Raised by a subcommand that has not been built yet."""


def _not_landed_parser(sub: argparse._SubParsersAction, name: str, help_: str) -> None:
    p = sub.add_parser(name, help=f"{help_} (not built yet)", add_help=True)
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    p.set_defaults(_run=lambda args, _n=name: _not_landed(_n))


def _not_landed(name: str) -> int:
    print(f"mcdenoise {name}: not built yet (its issue has not landed)", file=sys.stderr)
    return 2


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mcdenoise", description="Neural denoising of Monte Carlo renderings.")
    parser.add_argument("--version", action="version", version=f"mcdenoise {__version__}")
    parser.add_argument("--debug", action="store_true",
                        help="show the Python traceback of an error instead of the one-line message")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, help_ in SUBCOMMANDS.items():
        try:
            mod = importlib.import_module(f"mcdenoise.cli.{name}")
        except ModuleNotFoundError as e:
            if e.name != f"mcdenoise.cli.{name}":
                raise
            _not_landed_parser(sub, name, help_)
            continue
        p = sub.add_parser(name, help=help_, description=_first_paragraph(mod.__doc__ or help_))
        mod.add_parser(p)
        p.set_defaults(_run=mod.run)
    return parser


def _first_paragraph(doc: str) -> str:
    """The docstring's first paragraph as one line (its first line alone cut sentences short)."""
    return " ".join(doc.strip().split("\n\n", 1)[0].split())


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except BrokenPipeError:  # output piped into `head` and closed: not an error
        sys.stdout = open(os.devnull, "w")
        return 0
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except McDenoiseError as e:
        if args.debug:
            raise
        print(f"mcdenoise {args.command}: error: {_one_line(str(e))}", file=sys.stderr)
        return 1
    except OSError as e:
        # Operating-system errors the commands did not translate (permissions, full disk, a
        # path under a plain file...): still one line naming the path and the problem.
        if args.debug:
            raise
        from mcdenoise.io.safety import os_error

        print(f"mcdenoise {args.command}: error: {_one_line(str(os_error(e.filename or '?', e, 'writing or reading')))}",
              file=sys.stderr)
        return 1
    except Exception as e:  # a bug of ours or a library's: still one line; --debug shows the traceback
        if args.debug:
            raise
        print(f"mcdenoise {args.command}: internal error: {type(e).__name__}: {_one_line(str(e))} "
              "(run again with --debug for the traceback)", file=sys.stderr)
        return 1


def _one_line(text: str) -> str:
    """Messages keep to one line on stderr (a multi-line library message is joined)."""
    return " ".join(part.strip() for part in text.splitlines() if part.strip())


if __name__ == "__main__":
    sys.exit(main())
