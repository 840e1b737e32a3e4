"""Safe writes in one place: atomic replacement, writer locks, space checks, OS errors as one line.

Every writer of mcdenoise output goes through here:

* :func:`atomic_file` / :func:`atomic_dir` write under a hidden temporary sibling named
  ``.<name>.tmp-<host>-<pid>-<random>`` and rename it into place; on any error the temporary is
  removed. A temporary left by a killed run (same host, pid no longer alive) is removed by the
  next write into the same place (:func:`remove_stale_temps`).
* :func:`atomic_dir` with ``replaceable`` replaces an existing folder only when the predicate
  recognises it (e.g. :func:`is_mcdenoise_output`): ``--overwrite`` never deletes a user's folder.
* :class:`WriterLock` is a lock file holding the writer's pid and host; a lock whose process is
  gone (same host) is stale and taken over, a live one is refused in one line.
* :func:`check_space` compares the bytes a job will write with the free space and a cap.
* :func:`os_error` turns an ``OSError`` into one :class:`~mcdenoise.errors.OutputError` line.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import shutil
import socket
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from mcdenoise.errors import OutputError, OutputExistsError

__all__ = [
    "temp_sibling",
    "atomic_file",
    "atomic_dir",
    "remove_stale_temps",
    "is_mcdenoise_output",
    "check_output_path",
    "WriterLock",
    "check_space",
    "human_bytes",
    "os_error",
    "DEFAULT_MAX_BYTES",
]

#: Largest output a command writes unless told otherwise (``--max-gb``): 64 GB.
DEFAULT_MAX_BYTES = 64 * 10**9
#: Free space kept for everything else on the disk when checking a job's size.
_RESERVE = 64 * 2**20
_HOST = re.sub(r"[^A-Za-z0-9_]", "_", socket.gethostname())[:40] or "host"
_TEMP = re.compile(r"^\.(?P<stem>.*)\.(?P<tag>tmp|old)-(?P<host>[A-Za-z0-9_]+)-(?P<pid>\d+)-[0-9a-f]{8}")


def temp_sibling(path: str | os.PathLike, tag: str = "tmp") -> Path:
    """A unique hidden name in the same folder as ``path`` (same file system, so rename is atomic),
    carrying the writer's host and pid so a later run can tell a killed writer's leftover.

    The original suffix is kept last because some writers pick the format from the extension.
    """
    p = Path(path)
    return p.with_name(f".{p.stem}.{tag}-{_HOST}-{os.getpid()}-{uuid.uuid4().hex[:8]}{p.suffix}")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def _remove_tree(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    elif p.exists() or p.is_symlink():
        p.unlink(missing_ok=True)


def remove_stale_temps(path: str | os.PathLike) -> list[Path]:
    """Remove the temporaries of ``path`` left by killed writers on this host; returns them.

    Only names of our own pattern whose pid is dead on this same host are touched: a live writer's
    temporary, or one from another host (whose pids we cannot check), is left alone.
    """
    final = Path(path)
    parent = final.parent
    removed: list[Path] = []
    try:
        entries = list(parent.iterdir())
    except OSError:
        return removed
    for entry in entries:
        m = _TEMP.match(entry.name)
        if not m or m.group("stem") != final.stem or m.group("host") != _HOST:
            continue
        if int(m.group("pid")) == os.getpid() or _alive(int(m.group("pid"))):
            continue
        _remove_tree(entry)
        removed.append(entry)
    return removed


def os_error(path: str | os.PathLike, exc: OSError, doing: str = "writing") -> OutputError:
    """One line for an OS error met while ``doing`` something to ``path``."""
    where = exc.filename if isinstance(exc.filename, str) and exc.filename else os.fspath(path)
    reason = exc.strerror or str(exc) or type(exc).__name__
    hints = {
        errno.ENOSPC: "the disk is full",
        errno.EDQUOT: "the disk quota is exceeded",
        errno.EROFS: "the file system is read-only",
        errno.EACCES: "permission denied",
        errno.EPERM: "permission denied",
        errno.ENOTDIR: "a part of the path is a plain file, not a folder",
        errno.ENAMETOOLONG: "the name is too long",
    }
    hint = hints.get(exc.errno or -1)
    text = f"{doing} failed: {hint}" if hint else f"{doing} failed: {reason}"
    return OutputError(where, text)


@contextlib.contextmanager
def _translate(path: Path, doing: str) -> Iterator[None]:
    try:
        yield
    except OutputError:
        raise
    except OSError as exc:
        raise os_error(path, exc, doing) from exc


def _mkdir_parent(final: Path) -> None:
    with _translate(final.parent, "creating the folder"):
        final.parent.mkdir(parents=True, exist_ok=True)


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces ``path``, on error it is removed."""
    final = Path(path)
    _mkdir_parent(final)
    tmp = temp_sibling(final)
    try:
        yield tmp
        with _translate(final, "replacing the file"):
            os.replace(tmp, final)
    finally:
        if tmp.exists():
            tmp.unlink()


def is_mcdenoise_output(path: str | os.PathLike) -> bool:
    """True for a folder mcdenoise wrote: an image folder (meta.json of format mcdenoise-image) or a
    dataset (manifest.json or dataset.json of an mcdenoise format). Only these are replaced."""
    p = Path(path)
    if not p.is_dir() or p.is_symlink():
        return False
    for name in ("meta.json", "manifest.json", "dataset.json"):
        f = p / name
        if not f.is_file():
            continue
        try:
            doc = json.loads(f.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if isinstance(doc, dict) and str(doc.get("format", "")).startswith("mcdenoise-"):
            return True
    return False


def check_output_path(path: str | os.PathLike, *, overwrite: bool = False,
                      replaceable: Callable[[Path], bool] | None = is_mcdenoise_output) -> Path:
    """Refuse, in one line, an output path mcdenoise must not write or replace; returns it as a Path.

    Refused: an empty name or ``.``/``..`` (would replace the working folder), a path that cannot
    be encoded for the file system (non-UTF-8), a path under a plain file, an existing path without
    ``overwrite``, and with ``overwrite`` anything ``replaceable`` does not recognise.
    """
    text = os.fspath(path)
    if not str(text).strip():
        raise OutputError(repr(text), "empty output path")
    final = Path(path)
    if final.name in ("", ".", "..") or final.resolve() == Path.cwd().resolve():
        raise OutputError(text, "is the current folder (or its parent); name a new folder to write into")
    try:
        os.fsencode(final)
        str(final).encode("utf-8")
    except UnicodeError:
        raise OutputError(ascii(str(final)), "the path is not valid UTF-8; use another name") from None
    for parent in final.parents:
        if parent.exists() or parent.is_symlink():
            if not parent.is_dir():
                raise OutputError(text, f"{parent} is a plain file, not a folder")
            break
    if final.exists() or final.is_symlink():
        if not overwrite:
            raise OutputExistsError(text, "already exists (pass --overwrite to replace it)")
        if replaceable is not None and not replaceable(final):
            kind = "a plain file" if not final.is_dir() else "a folder mcdenoise did not write (no meta.json/manifest.json)"
            raise OutputError(text, f"is {kind}; --overwrite replaces only mcdenoise output: choose another --out")
    return final


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike, *, overwrite: bool = False,
               replaceable: Callable[[Path], bool] | None = None) -> Iterator[Path]:
    """Yield a temporary folder to fill; on success it is renamed to ``path``.

    With ``overwrite`` an existing ``path`` is moved aside first and deleted after the rename, so
    readers see either the old folder or the new one, never a half-written one. ``replaceable``
    (e.g. :func:`is_mcdenoise_output`) must accept an existing ``path`` before it is replaced;
    None accepts anything (callers replacing their own folders). Leftover temporaries of killed
    writers are removed first.
    """
    final = Path(path)
    _mkdir_parent(final)
    check_output_path(final, overwrite=overwrite, replaceable=replaceable)
    remove_stale_temps(final)
    tmp = temp_sibling(final, "tmp")
    with _translate(tmp, "creating the folder"):
        tmp.mkdir()
    try:
        yield tmp
        old = None
        if final.exists() or final.is_symlink():
            if not overwrite:
                raise OutputExistsError(final, "appeared while writing (pass --overwrite to replace it)")
            if replaceable is not None and not replaceable(final):
                raise OutputError(final, "was replaced by something mcdenoise did not write while writing; left alone")
            old = temp_sibling(final, "old")
            with _translate(final, "moving the old folder aside"):
                os.replace(final, old)
        with _translate(final, "renaming the new folder into place"):
            os.replace(tmp, final)
        if old is not None:
            _remove_tree(old)
    finally:
        if tmp.exists():
            _remove_tree(tmp)


class WriterLock:
    """An exclusive lock file for one writer of a place: ``{"pid", "host", "started", "what"}``.

    Taken with ``O_CREAT | O_EXCL`` (atomic on local and NFSv3+ file systems). A lock whose pid is
    dead on this host is stale (a killed run) and taken over; a live one, or one from another host,
    is refused with an :class:`OutputError` naming the holder. ``conflicts`` lets a caller share a
    folder between writers of disjoint parts: it is asked about every other live lock file that
    matches ``pattern`` (a glob in the lock's folder) and refuses when it returns True.
    """

    def __init__(self, path: str | os.PathLike, what: str = "", *, pattern: str | None = None,
                 conflicts: Callable[[dict[str, Any]], bool] | None = None) -> None:
        self.path = Path(path)
        self.what = what
        self.pattern = pattern
        self.conflicts = conflicts
        self._held = False

    def _read(self, p: Path) -> dict[str, Any] | None:
        try:
            doc = json.loads(p.read_text(encoding="utf-8"))
        except FileNotFoundError:
            return None
        except (OSError, ValueError):
            return {}
        return doc if isinstance(doc, dict) else {}

    def _stale(self, doc: dict[str, Any]) -> bool:
        try:
            return doc.get("host") == _HOST and not _alive(int(doc["pid"]))
        except (KeyError, TypeError, ValueError):
            return False

    def _refuse(self, p: Path, doc: dict[str, Any]) -> OutputError:
        who = f"pid {doc.get('pid', '?')} on host {doc.get('host', '?')}"
        what = f" ({doc['what']})" if doc.get("what") else ""
        return OutputError(p.parent, f"another mcdenoise run is writing here{what}: {who} holds {p.name} "
                                     "(wait for it, or delete the lock file if that run is gone)")

    def acquire(self) -> WriterLock:
        _mkdir_parent(self.path)
        if self.pattern is not None and self.conflicts is not None:
            for other in self.path.parent.glob(self.pattern):
                if other == self.path:
                    continue
                doc = self._read(other)
                if doc is None or self._stale(doc):
                    continue
                if self.conflicts(doc):
                    raise self._refuse(other, doc)
        body = json.dumps({"pid": os.getpid(), "host": _HOST, "started": time.time(), "what": self.what})
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                doc = self._read(self.path)
                if doc is None:
                    continue  # released meanwhile
                if self._stale(doc):
                    self.path.unlink(missing_ok=True)
                    continue
                raise self._refuse(self.path, doc) from None
            except OSError as exc:
                raise os_error(self.path, exc, "taking the writer lock") from exc
            with os.fdopen(fd, "w") as f:
                f.write(body)
            self._held = True
            return self
        raise OutputError(self.path, "could not take the writer lock (it keeps changing hands)")

    def release(self) -> None:
        if self._held:
            self._held = False
            self.path.unlink(missing_ok=True)

    def __enter__(self) -> WriterLock:
        return self.acquire()

    def __exit__(self, *exc: Any) -> None:
        self.release()


def human_bytes(n: float) -> str:
    """``1.5e9`` -> ``"1.5 GB"`` (decimal units, as ``df -H``)."""
    for unit in ("B", "kB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1000 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} PB"


def check_space(path: str | os.PathLike, nbytes: int, *, max_bytes: int | None = DEFAULT_MAX_BYTES,
                what: str = "the output") -> None:
    """Refuse (one line) to write ``nbytes`` under ``path`` when the disk lacks the space or when it
    exceeds ``max_bytes`` (None = no cap). Checked before anything is allocated."""
    p = Path(path)
    if max_bytes is not None and nbytes > max_bytes:
        raise OutputError(p, f"{what} would take {human_bytes(nbytes)}, more than the {human_bytes(max_bytes)} cap "
                             "(raise it with --max-gb, or render smaller)")
    probe = p
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    try:
        free = shutil.disk_usage(probe).free
    except OSError:
        return  # cannot tell (e.g. a path under a plain file): the write itself reports it
    if nbytes + _RESERVE > free:
        raise OutputError(p, f"{what} would take {human_bytes(nbytes)} but only {human_bytes(free)} is free there")
