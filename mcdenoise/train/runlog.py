"""What a run writes besides checkpoints: ``metrics.csv``, TensorBoard events, ``loss.png``.

``metrics.csv`` has one row per optimizer step (validation columns filled on validation steps).
Each row is written with one ``write`` and flushed, so a kill leaves at most a torn last line;
on resume the rows after the checkpoint's step (and any torn line) are dropped before appending.
Losses are written with ``repr`` so a resumed run can be compared bit for bit.
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any

import numpy as np

from mcdenoise.io.atomic import atomic_file

__all__ = ["METRICS_FILE", "VAL_METRICS", "COLUMNS", "MetricsLog", "read_metrics", "plot_loss"]

METRICS_FILE = "metrics.csv"
#: Validation metrics (names of :mod:`mcdenoise.eval.metrics`), logged as ``val_<name>``.
VAL_METRICS = ("relmse", "smape", "l1", "psnr")
COLUMNS = ("step", "phase", "loss", "lr", "grad_norm", "skipped", "crops_per_s", "s_per_step", "spp", "wall_s") + tuple(
    f"val_{m}" for m in VAL_METRICS
)


def _fmt(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v)
    return str(v)


def read_metrics(path: Path) -> list[dict[str, str]]:
    """Complete rows of ``metrics.csv`` (a torn last line or a short row is dropped)."""
    if not path.is_file():
        return []
    text = path.read_text()
    if text and not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]
    rows = list(csv.reader(io.StringIO(text)))
    if not rows or tuple(rows[0]) != COLUMNS:
        return []
    return [dict(zip(COLUMNS, r)) for r in rows[1:] if len(r) == len(COLUMNS)]


class MetricsLog:
    """Appends rows to ``metrics.csv`` and mirrors scalars to TensorBoard when it is installed."""

    def __init__(self, run_dir: Path, start_step: int, tensorboard: bool = True) -> None:
        self.path = Path(run_dir) / METRICS_FILE
        kept = [r for r in read_metrics(self.path) if int(r["step"]) <= start_step]
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(COLUMNS)
        for r in kept:
            w.writerow([r[c] for c in COLUMNS])
        with atomic_file(self.path) as tmp:
            tmp.write_text(buf.getvalue())
        self._f = open(self.path, "a", buffering=1)
        self._tb = None
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter
            except ImportError:  # tensorboard is optional
                SummaryWriter = None  # type: ignore[assignment,misc]
            if SummaryWriter is not None:
                self._tb = SummaryWriter(str(Path(run_dir) / "tensorboard"), purge_step=start_step + 1)

    def write(self, row: dict[str, Any]) -> None:
        """One row; keys from :data:`COLUMNS` (missing ones are left empty)."""
        unknown = set(row) - set(COLUMNS)
        if unknown:
            raise KeyError(f"metrics.csv has no columns {sorted(unknown)}")
        buf = io.StringIO()
        csv.writer(buf, lineterminator="\n").writerow([_fmt(row.get(c)) for c in COLUMNS])
        self._f.write(buf.getvalue())
        self._f.flush()
        if self._tb is not None:
            for k, v in row.items():
                if k != "step" and isinstance(v, (int, float)) and math.isfinite(v):
                    self._tb.add_scalar(k.replace("val_", "val/"), v, row["step"])

    def close(self) -> None:
        self._f.close()
        if self._tb is not None:
            self._tb.close()


# ----------------------------------------------------------------------------- loss.png

_W, _H, _PAD = 640, 360, 24
_LOSS_RGB = (40, 90, 200)
_SMOOTH_RGB = (10, 30, 90)
_VAL_RGB = (220, 60, 30)


def _line(img: np.ndarray, x0: float, y0: float, x1: float, y1: float, rgb: tuple[int, int, int]) -> None:
    n = int(max(abs(x1 - x0), abs(y1 - y0))) + 1
    xs = np.rint(np.linspace(x0, x1, n + 1)).astype(int)
    ys = np.rint(np.linspace(y0, y1, n + 1)).astype(int)
    ok = (xs >= 0) & (xs < img.shape[1]) & (ys >= 0) & (ys < img.shape[0])
    img[ys[ok], xs[ok]] = rgb


def _loss_points(rows: list[dict[str, str]]) -> list[tuple[int, float, str]]:
    """``(step, loss, phase)`` of every row with a positive finite loss (log-scale plottable)."""
    pts = [(int(r["step"]), float(r["loss"]), r.get("phase", "")) for r in rows if r["loss"] not in ("", "nan", "inf")]
    return [p for p in pts if p[1] > 0 and math.isfinite(p[1])]


def _val_points(rows: list[dict[str, str]]) -> list[tuple[int, float]]:
    """``(step, val_relmse)`` of every validation row with a positive finite value."""
    val = [(int(r["step"]), float(r["val_relmse"])) for r in rows if r.get("val_relmse") not in (None, "")]
    return [(s, v) for s, v in val if v > 0 and math.isfinite(v)]


def _plot_matplotlib(rows: list[dict[str, str]], out_png: Path) -> Path | None:
    """``loss.png`` with labelled axes: loss per step and its running mean (log y, left axis, one
    colour per training phase) and validation relMSE (right axis). None without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    pts = _loss_points(rows)
    if len(pts) < 2:
        return None
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=100)
    phases = list(dict.fromkeys(p[2] for p in pts))
    for i, ph in enumerate(phases):
        st = np.array([p[0] for p in pts if p[2] == ph], float)
        v = np.array([p[1] for p in pts if p[2] == ph])
        colour = f"C{i}"
        ax.plot(st, v, color=colour, alpha=0.3, lw=0.8)
        k = max(1, len(v) // 25)
        if len(v) >= k:
            ax.plot(st[k - 1 :], np.convolve(v, np.ones(k) / k, mode="valid"), color=colour, lw=1.8,
                    label=f"training loss ({ph})" if ph else "training loss")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("training loss")
    ax.grid(True, which="both", alpha=0.3)
    val = _val_points(rows)
    handles, labels = ax.get_legend_handles_labels()
    if val:
        ax2 = ax.twinx()
        ax2.plot([s for s, _ in val], [v for _, v in val], "o-", color="C3", ms=4, label="validation relMSE")
        ax2.set_yscale("log")
        ax2.set_ylabel("validation relMSE")
        h2, l2 = ax2.get_legend_handles_labels()
        handles, labels = handles + h2, labels + l2
    ax.legend(handles, labels, loc="upper right", fontsize=8)
    fig.tight_layout()
    with atomic_file(out_png) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return Path(out_png)


def plot_loss(metrics_path: Path, out_png: Path) -> Path | None:
    """Draw ``loss.png``: training loss per step, its running mean, and validation relMSE (own
    scale), log-scaled y, steps on x.

    With matplotlib (a dependency of the package) the axes are labelled; without it a plain
    numpy + zlib drawing without axis text is written (the numbers are in ``metrics.csv``).
    Returns None when there is nothing to plot yet.
    """
    from mcdenoise.io.exr import write_png
    from mcdenoise.io.safety import remove_stale_temps

    remove_stale_temps(out_png)  # a killed run's half-drawn .loss.tmp-*.png
    rows = read_metrics(metrics_path)
    drawn = _plot_matplotlib(rows, out_png)
    if drawn is not None:
        return drawn
    pts = _loss_points(rows)
    if len(pts) < 2:
        return None
    img = np.full((_H, _W, 3), 255, np.uint8)
    steps = np.array([p[0] for p in pts], float)
    logv = np.log10(np.array([p[1] for p in pts]))
    k = max(1, len(logv) // 50)
    smooth = np.convolve(logv, np.ones(k) / k, mode="valid")
    lo, hi = float(logv.min()), float(logv.max())
    hi = hi if hi > lo else lo + 1.0
    s0, s1 = float(steps.min()), float(steps.max())

    def x_of(s: float) -> float:
        return _PAD + (s - s0) / max(s1 - s0, 1.0) * (_W - 2 * _PAD)

    def y_of(v: float, a: float = lo, b: float = hi) -> float:
        return _H - _PAD - (v - a) / (b - a) * (_H - 2 * _PAD)

    # Decade grid lines, so the slope can be read without labels.
    for dec in range(math.floor(lo), math.ceil(hi) + 1):
        if lo <= dec <= hi:
            img[int(round(y_of(dec))), _PAD : _W - _PAD] = (225, 225, 225)
    _line(img, _PAD, _H - _PAD, _W - _PAD, _H - _PAD, (0, 0, 0))
    _line(img, _PAD, _PAD, _PAD, _H - _PAD, (0, 0, 0))
    light = tuple(int(255 - (255 - c) * 0.35) for c in _LOSS_RGB)
    for i in range(1, len(pts)):
        _line(img, x_of(steps[i - 1]), y_of(logv[i - 1]), x_of(steps[i]), y_of(logv[i]), light)  # type: ignore[arg-type]
    sx = steps[k - 1 :]
    for i in range(1, len(smooth)):
        _line(img, x_of(sx[i - 1]), y_of(smooth[i - 1]), x_of(sx[i]), y_of(smooth[i]), _SMOOTH_RGB)
    val = _val_points(rows)
    if val:
        lv = np.log10([v for _, v in val])
        a, b = float(lv.min()), float(lv.max())
        b = b if b > a else a + 1.0
        for (s, _), v in zip(val, lv):
            cx, cy = int(round(x_of(s))), int(round(y_of(v, a, b)))
            img[max(cy - 2, 0) : cy + 3, max(cx - 2, 0) : cx + 3] = _VAL_RGB
    return write_png(out_png, img)
