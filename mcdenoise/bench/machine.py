"""What a bench result says about the machine: CPU model, cores, memory, versions, thread
counts and load (:func:`machine_info`), and its practical convolution peak (:func:`peak_conv_gflops`)."""

from __future__ import annotations

import datetime
import os
import platform
from typing import Any

import torch
import torch.nn.functional as F

from mcdenoise.bench.timing import median_time, synchronizer

__all__ = ["machine_info", "peak_conv_gflops", "available_bytes"]


def machine_info(device: str, oidn_threads: int | None = None) -> dict[str, Any]:
    """CPU model, cores, memory, torch and OIDN versions and thread counts, load average, date."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((l.split(":", 1)[1].strip() for l in f if l.startswith("model name")), cpu)
    except OSError:
        pass
    info: dict[str, Any] = {
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "cpu": cpu, "cores": os.cpu_count(), "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(), "device": device,
    }
    try:
        with open("/proc/meminfo") as f:
            mem = {l.split(":")[0]: int(l.split()[1]) for l in f}
        info["memory_gib"] = round(mem["MemTotal"] / 2**20, 1)
    except (OSError, KeyError, ValueError):
        pass
    if hasattr(os, "getloadavg"):
        info["load_start"] = round(os.getloadavg()[0], 2)
    if device.startswith("cuda"):
        info["gpu"] = torch.cuda.get_device_name(torch.device(device))
    try:
        from mcdenoise.eval.oidn import version

        info["oidn"] = version()
        from mcdenoise.eval.oidn import device_threads

        info["oidn_threads"] = device_threads(oidn_threads)
    except Exception as e:  # noqa: BLE001 -- reported, not fatal: OIDN entries then fail alike
        info["oidn"] = f"unavailable ({e})"
    return info


def available_bytes() -> int:
    try:
        with open("/proc/meminfo") as f:
            mem = {l.split(":")[0]: int(l.split()[1]) for l in f}
        return mem["MemAvailable"] * 1024
    except (OSError, KeyError, ValueError):
        return 8 << 30


def peak_conv_gflops(channels: int, side: int, device: str, repeats: int = 5, precision: str = "float32") -> float:
    """GFLOP/s of one large 3x3 convolution ``(1, channels, side, side)``: the machine's practical
    peak for the layers our models are made of (a multiply-add counts 2). ``bfloat16``: in
    bfloat16 and channels_last, as the models' convolution trunks then run."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn((1, channels, side, side), generator=g).to(device)
    w = torch.randn((channels, channels, 3, 3), generator=g).to(device) * 0.01
    if precision == "bfloat16":
        x = x.to(torch.bfloat16, memory_format=torch.channels_last)
        w = w.to(torch.bfloat16, memory_format=torch.channels_last)
    flops = 2.0 * channels * channels * 9 * side * side
    sync = synchronizer(device)

    def call() -> None:
        with torch.inference_mode():
            F.conv2d(x, w, padding=1)
        sync()

    return flops / median_time(call, repeats, warmup=1) / 1e9
