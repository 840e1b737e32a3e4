"""Run the measurements of ``mcdenoise bench``; see :mod:`mcdenoise.bench.plan` for what and
docs/PERFORMANCE.md for the figures. Results are a JSON-ready dict (``run_bench``); tables are
made by :mod:`mcdenoise.bench.report`."""

from __future__ import annotations

import os
import statistics
import sys
import time
from typing import Any, Callable

import torch
from torch.utils.flop_counter import FlopCounterMode

from mcdenoise.bench.machine import available_bytes, machine_info, peak_conv_gflops
from mcdenoise.bench.memory import MEMORY_METHOD, peak_call_memory
from mcdenoise.bench.plan import ANCHOR_SPP, BenchConfig, Method, default_methods, priority
from mcdenoise.bench.timing import busy_warning, interleaved_times, median_time, synchronizer
from mcdenoise.data.channels import base_name, num_components
from mcdenoise.models.inference import inference_context, prepare_inference, resolve_precision
from mcdenoise.models.registry import build_model, synthetic_batch

__all__ = ["run_bench", "machine_info", "peak_conv_gflops", "shipped_weights", "api_arrays"]

Log = Callable[[str], None]


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


class _Channels:
    """Duck-typed stand-in for a model in :func:`synthetic_batch`: the union of several models'
    channels, so one set of inputs per (size, spp) serves every model (the inputs at 1080p and 8
    spp are gigabytes)."""

    def __init__(self, names: list[str], input_kind: str) -> None:
        self.names, self.input_kind = names, input_kind

    def required_channels(self) -> list[str]:
        return self.names


def _input_bytes(names: list[str], spp: int, width: int, height: int) -> int:
    return sum(num_components(base_name(n)) for n in names if n != "scene_features") * spp * width * height * 4


def _flops_per_pixel(model: torch.nn.Module, spp: int | None, device: str, side: int = 64) -> float:
    """Convolution/matmul FLOPs per output pixel of the model as timed (see models/info.py)."""
    batch = {k: v.to(device) for k, v in synthetic_batch(model, spp=spp or 1, height=side, width=side).items()}
    counter = FlopCounterMode(display=False)
    with inference_context(True), counter:
        model(batch)
    return counter.get_total_flops() / float(side * side)


def _train_throughput(m: Method, cfg: BenchConfig) -> dict[str, Any]:
    """Crops per second of full training steps (forward, loss, backward, clipped Adam) on
    synthetic crops already in memory: what the model costs, not the data loader."""
    from mcdenoise.train.config import TrainConfig
    from mcdenoise.train.trainer import Trainer

    torch.manual_seed(cfg.seed)
    model = build_model(m.name, m.preset).to(cfg.device)
    tcfg = TrainConfig(model=m.name, preset=m.preset, data="", steps=10**6, batch=cfg.train_batch,
                       crop=cfg.train_crop, workers=0).resolved(model.input_kind)
    trainer = Trainer(model, tcfg, torch.device(cfg.device))
    g = torch.Generator().manual_seed(cfg.seed)
    batch = synthetic_batch(model, batch=cfg.train_batch, spp=cfg.train_spp, height=cfg.train_crop,
                            width=cfg.train_crop, generator=g)
    batch["target"] = torch.rand((cfg.train_batch, 3, cfg.train_crop, cfg.train_crop), generator=g) + 0.1
    batch = {k: v.to(cfg.device) for k, v in batch.items()}
    sync = synchronizer(cfg.device)
    step = tcfg.steps - 1  # past KPCN's per-branch phase: the image loss, as most of training runs

    def call() -> None:
        trainer.step(batch, step)
        sync()

    s = median_time(call, cfg.train_steps, warmup=1)
    return {"method": m.label, "batch": cfg.train_batch, "crop": cfg.train_crop,
            "spp": cfg.train_spp if model.input_kind == "samples" else None,
            "s_per_step": s, "crops_per_s": cfg.train_batch / s}


def shipped_weights(m: Method) -> Any:
    """Path of ``m``'s shipped weights, or None when the package ships none for it."""
    from mcdenoise.models.weights import SHIPPED_DIR

    p = SHIPPED_DIR / f"{m.name}-{m.preset}.safetensors"
    return p if not m.is_oidn and p.is_file() else None


def api_arrays(model: torch.nn.Module, src: dict[str, torch.Tensor]) -> dict[str, Any]:
    """Keyword arguments of :func:`mcdenoise.denoise` holding ``src`` (a batch of one, as the bare
    call gets it) as numpy arrays, channel-first: ``color``, ``albedo``/``normal``/``depth`` when the
    model reads them, every other pixel channel in ``features``, sample buffers in ``samples``."""
    names = [n for n in model.required_channels() if n != "scene_features"]
    samples = model.input_kind == "samples"

    def px(name: str) -> Any:
        t = src[name][0]
        return (t.mean(0) if samples else t).detach().cpu().numpy()

    if "radiance" in src:
        color = px("radiance")
    else:  # KPCN reads diffuse and specular; the colour is their sum
        color = px("diffuse") + px("specular")
    kw: dict[str, Any] = {"color": color}
    features: dict[str, Any] = {}
    if samples:
        kw["samples"] = {n: src[n][0].detach().cpu().numpy() for n in names}
    else:
        for n in names:
            if n in ("albedo", "normal", "depth"):
                kw[n] = px(n)
            elif n != "radiance":
                features[n] = px(n)
    if "scene_features" in src:
        features["scene_features"] = src["scene_features"][0].detach().cpu().numpy()
    if features:
        kw["features"] = features
    return kw


class _Runner:
    def __init__(self, cfg: BenchConfig, log: Log) -> None:
        self.cfg, self.log = cfg, log
        methods = cfg.methods or default_methods()
        # A model with shipped weights is timed through the public API beside its bare call.
        self.methods = [a for m in methods for a in ([m, Method(m.name, m.preset, api=True)]
                                                     if cfg.api and not m.api and shipped_weights(m) else [m])]
        self.precision = resolve_precision(cfg.precision, cfg.device) if cfg.fast else "float32"
        self.models: dict[str, torch.nn.Module] = {}
        self.kind: dict[str, str] = {}
        for m in self.methods:
            if m.is_oidn:
                self.kind[m.label] = "oidn"
                continue
            if m.api:
                continue  # after its model (below)
            torch.manual_seed(cfg.seed)
            w = shipped_weights(m)
            if w is not None:  # the bare call runs the weights (and card config) its API row loads
                from mcdenoise.models.weights import load_denoiser

                model = load_denoiser(w)[0]
            else:
                model = build_model(m.name, m.preset)
            self.models[m.label] = prepare_inference(model.to(cfg.device), fast=cfg.fast, precision=self.precision)
            self.kind[m.label] = model.input_kind
        for m in self.methods:
            if m.api:
                self.kind[m.label] = self.kind[m.bare.label]
        self.measured: dict[tuple[str, int | None], tuple[int, float]] = {}  # -> (pixels, seconds)
        self.entries: list[dict[str, Any]] = []
        self.flops: dict[tuple[str, int | None], float] = {}

    # -- planning ---------------------------------------------------------------------------
    def _estimate(self, label: str, spp: int | None, pixels: int) -> float | None:
        got = self.measured.get((label, spp))
        return None if got is None else got[1] * pixels / got[0]

    def _plan(self, w: int, h: int, first: bool, budget: float) -> tuple[list[tuple[Method, int | None]], float]:
        cfg = self.cfg
        spps = sorted(cfg.spp, key=lambda s: (s != ANCHOR_SPP, s))
        cands: list[tuple[Method, int | None]] = []
        for m in self.methods:
            if self.kind[m.label] == "samples":
                cands += [(m, s) for s in spps]
            else:
                cands.append((m, None))
        if first:
            return cands, 0.0
        keyed = []
        for m, s in cands:
            est = self._estimate(m.label, s, w * h)
            keyed.append((priority(m, s, (w, h), cfg.target_size), est if est is not None else float("inf"), m, s))
        keyed.sort(key=lambda t: (t[0], t[1]))
        chosen, spent = [], 0.0
        for prio, est, m, s in keyed:
            # A slow entry makes one warm-up call and one timed round (see _group).
            cost = est * (2 if est > cfg.slow_s else cfg.warmup + cfg.rounds)
            if prio == 0 or spent + cost <= budget:
                chosen.append((m, s))
                spent += cost if cost != float("inf") else 0.0
            else:
                why = "not measured at a smaller size" if est == float("inf") else \
                    f"estimated {est:.1f} s per call, over the time budget left for this size"
                self._skip(m, s, w, h, why)
        return chosen, spent

    def _skip(self, m: Method, spp: int | None, w: int, h: int, why: str) -> None:
        self.entries.append({"method": m.label, "width": w, "height": h, "spp": spp, "status": "skipped", "reason": why})

    # -- inputs -----------------------------------------------------------------------------
    def _inputs(self, labels: list[str], kind: str, spp: int, w: int, h: int) -> dict[str, torch.Tensor]:
        names: list[str] = []
        for lb in labels:
            names += [n for n in self.models[lb].required_channels() if n not in names]
        g = torch.Generator().manual_seed(self.cfg.seed + spp)
        b = synthetic_batch(_Channels(names, kind), spp=spp, height=h, width=w, generator=g)  # type: ignore[arg-type]
        return {k: v.to(self.cfg.device) for k, v in b.items()}

    def _oidn_inputs(self, w: int, h: int) -> dict[str, Any]:
        g = torch.Generator().manual_seed(self.cfg.seed)
        b = synthetic_batch(_Channels(["radiance", "albedo", "normal"], "pixels"), height=h, width=w, generator=g)  # type: ignore[arg-type]
        return {k: v[0].numpy() for k, v in b.items()}

    # -- one group of entries timed in the same rounds --------------------------------------
    def _group(self, entries: list[tuple[Method, int | None]], spp: int, w: int, h: int) -> None:
        cfg = self.cfg
        calls: dict[str, Callable[[], Any]] = {}
        keys: dict[str, tuple[Method, int | None]] = {}
        by_kind: dict[str, list[str]] = {"pixels": [], "samples": []}
        for m, s in entries:
            if not m.is_oidn and m.bare.label not in by_kind[self.kind[m.label]]:
                by_kind[self.kind[m.label]].append(m.bare.label)
        inputs: dict[str, dict[str, torch.Tensor]] = {}
        avail = available_bytes()
        for kind, labels in by_kind.items():
            if not labels:
                continue
            names = sorted({n for lb in labels for n in self.models[lb].required_channels()})
            need = _input_bytes(names, spp if kind == "samples" else 1, w, h)
            if need > cfg.memory_fraction * avail:
                for m, s in entries:
                    if not m.is_oidn and self.kind[m.label] == kind:
                        self._skip(m, s, w, h, f"inputs {need / 2**30:.1f} GiB > {cfg.memory_fraction:.0%} of available memory")
                entries = [(m, s) for m, s in entries if m.is_oidn or self.kind[m.label] != kind]
                continue
            inputs[kind] = self._inputs(labels, kind, spp if kind == "samples" else 1, w, h)
        oidn_in = self._oidn_inputs(w, h) if any(m.is_oidn for m, _ in entries) else None
        for m, s in entries:
            name = f"{m.label}@{s}" if s is not None else m.label
            keys[name] = (m, s)
            if m.is_oidn:
                from mcdenoise.eval.oidn import oidn_denoise, parse_quality

                quality, prefilter = parse_quality(m.preset)
                calls[name] = lambda q=quality, pf=prefilter: oidn_denoise(
                    oidn_in["radiance"], oidn_in["albedo"], oidn_in["normal"], quality=q, threads=self.cfg.oidn_threads,
                    prefilter=pf)
            elif m.api:
                import mcdenoise

                kw = api_arrays(self.models[m.bare.label], inputs[self.kind[m.label]])
                calls[name] = lambda kw=kw, w=str(shipped_weights(m)): mcdenoise.denoise(
                    **kw, model=w, device=cfg.device, precision=self.precision)
            else:
                model = self.models[m.label]
                src = inputs[self.kind[m.label]]
                batch = {k: src[k] for k in model.required_channels() if k != "scene_features"}
                if "scene_features" in src:
                    batch["scene_features"] = src["scene_features"]

                def call(model: torch.nn.Module = model, batch: dict = batch) -> Any:
                    with inference_context(cfg.fast):
                        return model(batch)

                calls[name] = call
        peaks: dict[str, int | None] = {}
        ok: dict[str, Callable[[], Any]] = {}
        caps: dict[str, int] = {}
        sync = synchronizer(cfg.device)
        first_size = (w, h) == tuple(cfg.sizes[0])
        for name, fn in calls.items():  # warm-up; the first call also measures peak memory
            try:
                for i in range(cfg.warmup):
                    t0 = time.perf_counter()
                    if i == 0:
                        _, peaks[name] = peak_call_memory(lambda: (fn(), sync()), cfg.device)
                    else:
                        fn()
                        sync()
                    if not first_size and time.perf_counter() - t0 > cfg.slow_s:
                        caps[name] = 1  # a slow call: one more warm-up would cost more than it settles
                        break
                ok[name] = fn
            except Exception as e:  # noqa: BLE001 -- one failed entry is reported, the others still run
                m, s = keys[name]
                self.entries.append({"method": m.label, "width": w, "height": h, "spp": s, "status": "error",
                                     "reason": " ".join(str(e).split())[:200]})
        groups = {name: ("oidn" if keys[name][0].is_oidn else "torch") for name in ok}
        times = interleaved_times(ok, cfg.rounds, sync=sync, max_rounds=caps, groups=groups)
        for name, ts in times.items():
            m, s = keys[name]
            med = statistics.median(ts)
            self.measured[(m.label, s)] = (w * h, med)
            row: dict[str, Any] = {"method": m.label, "width": w, "height": h, "spp": s, "status": "ok",
                                   "median_s": med, "times_s": ts, "peak_bytes": peaks.get(name)}
            if not m.is_oidn and not m.api:
                key = (m.label, s)
                if key not in self.flops:
                    self.flops[key] = _flops_per_pixel(self.models[m.label], s, cfg.device)
                row["flops_per_pixel"] = self.flops[key]
            self.entries.append(row)
            self.log(f"  {w}x{h} {name}: {med * 1e3:.1f} ms" + (f", peak {peaks[name] / 2**20:.0f} MiB" if peaks.get(name) is not None else ""))

    def run(self) -> None:
        cfg = self.cfg
        sizes = list(cfg.sizes)
        budget = cfg.budget_s
        for i, (w, h) in enumerate(sizes):
            rest_px = sum(a * b for a, b in sizes[i:])
            share = budget * w * h / rest_px if i else 0.0
            chosen, planned = self._plan(w, h, i == 0, share)
            t0 = time.perf_counter()
            spps = sorted(cfg.spp, key=lambda s: (s != ANCHOR_SPP, s))
            anchor = spps[0]
            for spp in spps:
                group = [(m, s) for m, s in chosen if s == spp or (spp == anchor and s is None)]
                if group:
                    self.log(f"{w}x{h}, {spp} spp: {len(group)} entries")
                    self._group(group, spp, w, h)
            if i:
                budget = max(0.0, budget - (time.perf_counter() - t0))


def run_bench(cfg: BenchConfig, log: Log = _stderr) -> dict[str, Any]:
    """Every measurement of one bench run, as a JSON-ready dict (see module docstring)."""
    t0 = time.perf_counter()
    info = machine_info(cfg.device, cfg.oidn_threads)
    precision = resolve_precision(cfg.precision, cfg.device) if cfg.fast else "float32"
    log(f"bench on {info['cpu']} ({info['cores']} cores, {info['torch_threads']} torch threads, "
        f"{info.get('oidn_threads', '?')} OIDN threads), device {cfg.device}, precision {precision}")
    busy = busy_warning("at start", info.get("load_start"))
    if busy:
        log(f"warning: {busy}")
    gflops = peak_conv_gflops(cfg.peak_conv[0], cfg.peak_conv[1], cfg.device, precision=precision)
    log(f"peak 3x3 conv {cfg.peak_conv[0]} channels ({precision}): {gflops:.1f} GFLOP/s")
    runner = _Runner(cfg, log)
    runner.run()
    training = []
    if cfg.train_steps > 0:
        for m in runner.methods:
            if m.is_oidn or m.api:
                continue
            try:
                training.append(_train_throughput(m, cfg))
                log(f"  train {m.label}: {training[-1]['crops_per_s']:.1f} crops/s")
            except Exception as e:  # noqa: BLE001 -- reported in the table
                training.append({"method": m.label, "error": " ".join(str(e).split())[:200]})
    info["load_end"] = round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None
    busy = busy_warning("at end", info["load_end"]) if info["load_end"] is not None else None
    if busy:
        log(f"warning: {busy}")
    params = {lb: sum(p.numel() for p in mdl.parameters()) for lb, mdl in runner.models.items()}
    return {
        "machine": info,
        "config": {"sizes": [list(s) for s in cfg.sizes], "spp": list(cfg.spp), "warmup": cfg.warmup,
                   "rounds": cfg.rounds, "budget_s": cfg.budget_s, "fast": cfg.fast, "device": cfg.device, "api": cfg.api,
                   "precision": runner.precision, "slow_s": cfg.slow_s,
                   "methods": [m.label for m in runner.methods], "train": {"batch": cfg.train_batch,
                   "crop": cfg.train_crop, "spp": cfg.train_spp, "steps": cfg.train_steps}},
        "memory_method": MEMORY_METHOD if not cfg.device.startswith("cuda") else "torch.cuda.max_memory_allocated above the allocation before the call",
        "peak_conv": {"channels": cfg.peak_conv[0], "side": cfg.peak_conv[1], "gflops": gflops, "precision": precision},
        "parameters": params,
        "entries": runner.entries,
        "training": training,
        "wall_s": time.perf_counter() - t0,
    }
