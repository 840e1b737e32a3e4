"""Generated blocks inside hand-written Markdown: ``docs/RESULTS.md`` is written by commands.

A block is the text between ``<!-- BEGIN generated:KEY -->`` and ``<!-- END generated:KEY -->``.
``mcdenoise eval`` owns the ``eval:...`` keys and each ``mcdenoise repro NAME`` its
``repro:NAME`` key, so several commands fill one document without overwriting each other's
tables or the prose around them. The file is replaced atomically.
"""

from __future__ import annotations

import re
from pathlib import Path

from mcdenoise.io.atomic import atomic_file

__all__ = ["replace_block", "read_block"]


def _markers(key: str) -> tuple[str, str]:
    if not re.fullmatch(r"[A-Za-z0-9_.:/-]+", key):
        raise ValueError(f"block key {key!r} may hold only letters, digits and _.:/-")
    return f"<!-- BEGIN generated:{key} -->", f"<!-- END generated:{key} -->"


def read_block(path: str | Path, key: str) -> str | None:
    """The text of block ``key`` in ``path`` (without markers), or None when absent."""
    p = Path(path)
    if not p.is_file():
        return None
    begin, end = _markers(key)
    text = p.read_text()
    i, j = text.find(begin), text.find(end)
    if i < 0 or j < i:
        return None
    return text[i + len(begin):j].strip("\n")


def replace_block(path: str | Path, key: str, body: str, *, heading: str | None = None) -> Path:
    """Put ``body`` into block ``key`` of ``path``: in place when the block exists, else appended
    (after ``heading``, a Markdown line such as ``"## Reproductions"``, when given). Creates the file."""
    p = Path(path)
    begin, end = _markers(key)
    text = p.read_text() if p.is_file() else ""
    block = f"{begin}\n{body.strip(chr(10))}\n{end}"
    i, j = text.find(begin), text.find(end)
    if i >= 0 and j > i:
        text = text[:i] + block + text[j + len(end):]
    else:
        sep = "" if not text or text.endswith("\n\n") else ("\n" if text.endswith("\n") else "\n\n")
        text = text + sep + (f"{heading}\n\n" if heading else "") + block + "\n"
    p.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(p) as tmp:
        tmp.write_text(text)
    return p
