"""Where a report's numbers came from: versions, machine, date (``provenance`` in results.json)."""

from __future__ import annotations

import datetime
import os
import platform
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["provenance"]


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def provenance(device: torch.device, oidn: bool) -> dict[str, Any]:
    """Versions and machine behind the numbers."""
    from importlib import metadata

    import mcdenoise

    out: dict[str, Any] = {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "mcdenoise": mcdenoise.__version__,
        "torch": torch.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu": _cpu_name(),
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "device": str(device),
    }
    if device.type == "cuda":
        out["gpu"] = torch.cuda.get_device_name(device)
    if oidn:
        from mcdenoise.eval.oidn import version

        out["oidn"] = version()
        try:
            out["pyoidn"] = metadata.version("pyoidn")
        except metadata.PackageNotFoundError:
            pass
    out["machine"] = f"{out['cpu']} ({out['cpu_count']} logical cores)" + (f", {out['gpu']}" if "gpu" in out else "")
    return out
