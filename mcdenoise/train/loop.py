"""The training loop shared by every registered model: ``mcdenoise train`` and :func:`train`.

One process or several (``torchrun``): each rank builds the same model from ``cfg.seed``, reads its
rows of every global batch (:mod:`mcdenoise.train.data`), and DistributedDataParallel averages the
gradients, so N ranks with ``batch / N`` rows each compute the same update as one process with
``batch`` rows (up to float summation order). Rank 0 alone writes the run folder.

Exact resume: batch ``t`` is a pure function of ``(seed, t)``, the schedule a pure function of
``t``, and a checkpoint holds the weights, Adam's state and the RNG state after step ``t``; on CPU
a resumed run therefore reproduces the losses of an uninterrupted one bit for bit.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, is_dataclass
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist

from mcdenoise.errors import McDenoiseError
from mcdenoise.io.atomic import atomic_file
from mcdenoise.io.safety import WriterLock
from mcdenoise.io.run_folder import CONFIG_FILE, RESULT_FILE, WEIGHTS_FILE, checkpoint_folder_name
from mcdenoise.models.registry import Denoiser, build_model
from mcdenoise.models.weights import WeightsError, model_from_config
from mcdenoise.train.checkpoint import CHECKPOINT_DIR, Checkpoint, intact_checkpoint, load_checkpoint, prune_checkpoints, \
    resume_checkpoint, save_checkpoint, state_dict_for_safetensors
from mcdenoise.train.config import ConfigError, TrainConfig, check_resume_config, config_document, manifest_hash, read_config
from mcdenoise.data.dataset import dataset_dirs
from mcdenoise.train.data import batch_source, training_batches, validation_batches
from mcdenoise.train.optim import StepOutcome, lr_at
from mcdenoise.train.runlog import MetricsLog, plot_loss
from mcdenoise.train.trainer import Trainer, data_config

__all__ = ["train", "TrainResult", "prepare_run_dir", "CONFIG_FILE", "WEIGHTS_FILE"]


@dataclass
class TrainResult:
    """What :func:`train` returns (rank 0's view).

    Attributes:
        run_dir: the run folder; step: steps completed; skipped: updates dropped as non-finite;
        wall_s: seconds spent in this call; val: the last validation metrics (may be empty).
    """

    run_dir: Path
    step: int
    skipped: int
    wall_s: float
    val: dict[str, float]


# ----------------------------------------------------------------------------- distributed set-up


def _dist_env() -> tuple[int, int, int]:
    """(rank, world_size, local_rank) from torchrun's environment; (0, 1, 0) without it."""
    return int(os.environ.get("RANK", 0)), int(os.environ.get("WORLD_SIZE", 1)), int(os.environ.get("LOCAL_RANK", 0))


def _device(cfg: TrainConfig, local_rank: int) -> torch.device:
    want = cfg.device
    if want == "auto":
        want = "cuda" if torch.cuda.is_available() else "cpu"
    if want == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError("--device cuda: no CUDA device is available")
        torch.cuda.set_device(local_rank)  # before the process group, so nccl binds the right GPU
        return torch.device("cuda", local_rank)
    if want != "cpu":
        raise ConfigError(f"device must be cpu, cuda or auto, got {cfg.device!r}")
    return torch.device("cpu")


def _init_distributed(device: torch.device, world: int) -> bool:
    """Join torchrun's process group (nccl on CUDA, gloo on CPU); False when single-process."""
    if world <= 1:
        return False
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    return True


# ----------------------------------------------------------------------------- run folder


def _model_config_json(model: Denoiser) -> dict[str, Any]:
    c = model.config
    d = asdict(c) if is_dataclass(c) else dict(vars(c))
    return json.loads(json.dumps(d, default=list))  # tuples -> lists, as they read back


def _init_model(cfg: TrainConfig) -> Denoiser:
    """The model of ``cfg.init`` (fine-tuning), in training mode; refuses another model family,
    a preset that differs from the one asked for, and overrides (the weights fix the architecture)."""
    from mcdenoise.models.weights import load_denoiser, preset_differences

    if cfg.model_overrides:
        raise ConfigError("--init takes the architecture from its weights: model overrides cannot be combined with it")
    model, info = load_denoiser(cfg.init)
    if info["name"] != cfg.model:
        raise ConfigError(f"--init {cfg.init}: holds {info['name']} weights, the run trains {cfg.model}")
    # A run trained with --model-overrides that equal another preset may seed that preset.
    if info["preset"] != cfg.preset and preset_differences(cfg.model, cfg.preset, _model_config_json(model)):
        raise ConfigError(f"--init {cfg.init}: preset {info['preset']}, the run asks for {cfg.preset} (pass --preset {info['preset']})")
    return model.float().train()


def prepare_run_dir(out: Path, doc: dict[str, Any], *, resume: bool, force: bool) -> tuple[int, bool]:
    """Create or check the run folder (rank 0 only). Returns ``(start_step, fresh)``.

    Refuses, with one line: an existing run without ``--resume``/``--force``; a resume whose
    config differs; a non-empty folder that is not a run (even with ``--force``: it is not ours
    to delete).
    """
    cfg_path = out / CONFIG_FILE
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: exists and is not a folder")
    is_run = cfg_path.is_file()
    if out.is_dir() and not is_run and any(out.iterdir()):
        raise ConfigError(f"{out}: not empty and not a run folder (no {CONFIG_FILE}); choose another --out")
    if is_run and resume:
        saved = read_config(cfg_path)
        check_resume_config(saved, doc, cfg_path)
        ck = intact_checkpoint(out)
        if saved["train"].get("steps") != doc["train"]["steps"]:
            print(f"{out}: extending the run from {saved['train'].get('steps')} to {doc['train']['steps']} steps "
                  "(learning-rate schedule laid over the new total)", file=sys.stderr)
            with atomic_file(cfg_path) as tmp:
                tmp.write_text(json.dumps({**saved, "train": {**saved["train"], "steps": doc["train"]["steps"]}}, indent=1) + "\n")
        return (ck.step if ck else 0), False
    if is_run and not force:
        raise ConfigError(f"{out}: a run already exists; pass --resume to continue it or --force to start over")
    if is_run:
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_file(cfg_path) as tmp:
        tmp.write_text(json.dumps(doc, indent=1) + "\n")
    return 0, True


def run_lock_path(out: Path) -> Path:
    """The writer lock of run folder ``out``: ``.<name>.train.lock`` beside it."""
    out = Path(out).resolve()
    return out.parent / f".{out.name}.train.lock"


def _broadcast_start(start: int, ok: bool, distributed: bool, device: torch.device) -> int:
    """Share rank 0's start step (or its refusal) with every rank."""
    if not distributed:
        return start
    t = torch.tensor([start, int(ok)], dtype=torch.int64, device=device)  # nccl needs CUDA tensors
    dist.broadcast(t, 0)
    if not t[1]:
        raise ConfigError("rank 0 refused the run folder (see its error)")
    return int(t[0])


def _progress(total: int, initial: int, enabled: bool) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, disable=not enabled, unit="step", dynamic_ncols=True, file=sys.stderr)


def train(
    cfg: TrainConfig,
    out: str | os.PathLike,
    *,
    resume: bool = False,
    force: bool = False,
    on_step: Callable[[int, StepOutcome], None] | None = None,
) -> TrainResult:
    """Train ``cfg.model`` on ``cfg.data`` into run folder ``out`` (see module docstring).

    Args:
        cfg: settings; ``None`` fields are resolved from the model's defaults.
        resume: continue from the newest checkpoint of ``out`` (a missing folder starts fresh).
        force: replace an existing run folder.
        on_step: called after every step with ``(steps_done, outcome)`` (tests, notebooks).
    """
    t_start = time.perf_counter()
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    rank, world, local_rank = _dist_env()
    device = _device(cfg, local_rank)
    distributed = _init_distributed(device, world)
    locks: list[WriterLock] = []
    try:
        return _train(cfg, Path(out), resume, force, on_step, rank, world, device, distributed, t_start, locks)
    finally:
        for lock in locks:
            lock.release()
        if distributed and dist.is_initialized():
            dist.destroy_process_group()


def _train(cfg: TrainConfig, out: Path, resume: bool, force: bool, on_step: Callable[[int, StepOutcome], None] | None,
           rank: int, world: int, device: torch.device, distributed: bool, t_start: float,
           locks: list[WriterLock]) -> TrainResult:
    try:
        dirs = dataset_dirs(cfg.data)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    for d in dirs:
        if not (d / "manifest.json").is_file():
            raise ConfigError(f"{d}: not a dataset folder (no manifest.json); make one with `mcdenoise dataset`")
    data_dir = cfg.data  # one folder, or several separated by commas: the readers take either
    if cfg.batch % world:
        raise ConfigError(f"batch {cfg.batch} is not divisible by the {world} processes")
    torch.manual_seed(cfg.seed)
    try:
        if cfg.init:
            model = _init_model(cfg)
        else:
            model = (model_from_config(cfg.model, cfg.preset, cfg.model_overrides) if cfg.model_overrides
                     else build_model(cfg.model, cfg.preset))
    except KeyError as e:
        raise ConfigError(str(e.args[0])) from None
    except WeightsError as e:  # an override names a field the model's config lacks
        raise ConfigError(str(e)) from None
    cfg = cfg.resolved(model.input_kind)
    doc = config_document(cfg, model_config=_model_config_json(model), manifest_sha256=manifest_hash(cfg.data), world_size=world)
    # Check the data against the settings (crop larger than an image, spp out of range...) before
    # the run folder exists, so a typo does not leave a run that then needs --force.
    err: ConfigError | None = None
    val_batches: list[dict[str, torch.Tensor]] = []
    try:
        batch_source(data_dir, model, data_config(cfg), rank=rank, world_size=world)
        if rank == 0:
            val_batches = validation_batches(cfg.val_data or data_dir, model, data_config(cfg),
                                             max_images=cfg.val_images)
    except ValueError as e:
        err = ConfigError(str(e))
    if distributed:  # every rank stops if any rank cannot read its data
        flag = torch.tensor([0 if err else 1], device=device)  # nccl reduces CUDA tensors only
        dist.all_reduce(flag, op=dist.ReduceOp.MIN)
        if not flag[0] and err is None:
            err = ConfigError("another process refused the data (see its error)")
    if err is not None:
        raise err

    start = 0
    st: dict[str, Any] | None = None
    if rank == 0:
        try:
            # One writer per run folder: a second --resume or --force while this run lives is
            # refused in one line (the lock sits beside the folder, so --force's rmtree keeps it).
            locks.append(WriterLock(run_lock_path(out), f"train {out.name}").acquire())
            _, fresh = prepare_run_dir(out, doc, resume=resume, force=force)
            if not fresh:  # the newest intact checkpoint (damaged newer ones are named and passed over)
                ck, st = resume_checkpoint(out, model, "cpu")
                start = ck.step if ck is not None else 0
        except McDenoiseError:
            _broadcast_start(0, False, distributed, device)
            raise
    start = _broadcast_start(start, True, distributed, device)

    model.to(device)
    trainer = Trainer(model, cfg, device, distributed)
    if rank == 0 and 0 < start < cfg.steps:
        print(f"{out}: resuming at step {start} of {cfg.steps}", file=sys.stderr)
    if rank == 0 and val_batches and start < cfg.steps:
        base = Trainer.noisy_baseline(val_batches)
        shown = ", ".join(f"{k} {v:.4g}" for k, v in base.items())
        print(f"{out}: validation on {len(val_batches)} image(s) of {cfg.val_data or cfg.data}; "
              f"the noisy input scores {shown}", file=sys.stderr)
    skipped = 0
    wall_before = 0.0  # wall time of earlier calls, up to the checkpoint resumed from
    if start > 0:
        if st is None:  # the other ranks load the checkpoint rank 0 chose
            st = load_checkpoint(Checkpoint(out / CHECKPOINT_DIR / checkpoint_folder_name(start), start), model, device)
        skipped = trainer.load_state(st)
        wall_before = float(st.get("wall_s", 0.0))
    if start >= cfg.steps:
        if rank == 0:
            print(f"{out}: already trained for {start} steps", file=sys.stderr)
            if not (out / WEIGHTS_FILE).is_file():  # killed between the last checkpoint and the final write
                _write_final(out, model, cfg, device, world, skipped, wall_before, 0.0, {})
        return TrainResult(out, start, skipped, time.perf_counter() - t_start, {})

    log = MetricsLog(out, start) if rank == 0 else None
    batches: Iterator[dict[str, torch.Tensor]] = training_batches(
        data_dir, model, data_config(cfg), start_step=start, rank=rank, world_size=world, device=device
    )
    bar = _progress(cfg.steps, start, cfg.progress and rank == 0)
    val: dict[str, float] = {}
    ema: float | None = None
    t_prev = time.perf_counter()
    try:
        for t in range(start, cfg.steps):
            batch = next(batches)
            outcome = trainer.step(batch, t)
            skipped += outcome.skipped
            done = t + 1
            now = time.perf_counter()
            dt, t_prev = now - t_prev, now
            if on_step is not None:
                on_step(done, outcome)
            if rank != 0:
                continue
            assert log is not None
            row: dict[str, Any] = {"step": done, "phase": trainer.phase(t), "loss": outcome.loss, "lr": lr_at(t, cfg),
                                   "grad_norm": outcome.grad_norm, "skipped": skipped, "crops_per_s": cfg.batch / dt,
                                   "s_per_step": dt, "spp": float(batch["spp"].float().mean()) if "spp" in batch else None,
                                   "wall_s": wall_before + now - t_start}
            if outcome.skipped:
                print(f"step {done}: non-finite loss or gradient, update skipped ({skipped} so far)", file=sys.stderr)
            last = done == cfg.steps
            validating = bool(cfg.val_every and done % cfg.val_every == 0) or last
            if validating:
                val = trainer.validate(val_batches)
                row.update({f"val_{k}": v for k, v in val.items()})
            log.write(row)
            if done % cfg.checkpoint_every == 0 or last:
                save_checkpoint(out, done, model, trainer.state(done, skipped, wall_before + now - t_start))
                prune_checkpoints(out, cfg.keep_every)
            if validating:
                plot_loss(log.path, out / "loss.png")
            if math.isfinite(outcome.loss):
                ema = outcome.loss if ema is None else 0.9 * ema + 0.1 * outcome.loss
            bar.set_postfix(loss=f"{ema:.4g}" if ema is not None else "nan", crops_s=f"{cfg.batch / dt:.1f}")
            bar.update(1)
            # Validation and checkpoint time is not the next step's: restart its clock here.
            t_prev = time.perf_counter()
    finally:
        bar.close()
        if log is not None:
            log.close()
        batches.close()  # shuts the loader's worker processes down now, not at garbage collection
    wall = time.perf_counter() - t_start
    if rank == 0:
        _write_final(out, model, cfg, device, world, skipped, wall_before, wall, val)
    if distributed:
        # Every rank tears its process group down together, after rank 0's last write: a rank
        # that destroyed gloo while its peer was still writing aborted at exit now and then
        # ("terminate called without an active exception", seen once under load in CI).
        dist.barrier()
    return TrainResult(out, cfg.steps, skipped, wall, val)


def _cpu_seconds() -> float:
    """User+system CPU seconds of this process and its finished children (the loader workers,
    joined before this is called): on a shared machine the honest measure of training cost."""
    import resource

    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _write_final(out: Path, model: Denoiser, cfg: TrainConfig, device: torch.device, world: int, skipped: int,
                 wall_before: float, wall: float, val: dict[str, float]) -> None:
    """``model.safetensors`` (final weights) and ``result.json``, each atomically."""
    from safetensors.torch import save_file

    with atomic_file(out / WEIGHTS_FILE) as tmp:
        # The architecture travels with the file: a run trained with overrides or from a reconfigured
        # --init loads by its path alone, not only through its run folder.
        save_file(state_dict_for_safetensors(model), str(tmp), metadata={
            "model": cfg.model, "preset": cfg.preset, "step": str(cfg.steps),
            "model_config": json.dumps(_model_config_json(model))})
    summary = {"model": cfg.model, "preset": cfg.preset, "steps": cfg.steps, "skipped": skipped, "device": str(device),
               "world_size": world, "wall_s": wall_before + wall, "wall_s_this_call": wall,
               "cpu_s_this_call": _cpu_seconds(), "val": val}
    with atomic_file(out / RESULT_FILE) as tmp:
        tmp.write_text(json.dumps(summary, indent=1) + "\n")
