"""The methods an evaluation compares: the noisy input, OIDN per quality, NL-means, then each
model in each precision, with unique labels."""

from __future__ import annotations

import os
from collections.abc import Sequence

import torch

from mcdenoise.errors import EvalError
from mcdenoise.eval.methods import ClassicMethod, Method, ModelMethod, NoisyMethod, OIDNMethod

__all__ = ["build_methods"]


def build_methods(models: Sequence[str | os.PathLike], oidn: Sequence[str], classic: bool,
                  device: torch.device, precisions: Sequence[str] = ("float32",), oidn_threads: int | None = None,
                  notes: list[str] | None = None, self_ensemble: bool = False) -> list[Method]:
    """Noisy, OIDN per quality (on ``oidn_threads`` threads; default every core), NL-means, then
    each model in each precision; a bfloat16 run of a model is labelled ``LABEL+bf16``. With
    ``self_ensemble`` each model also runs as a self-ensemble (:mod:`mcdenoise.models.symmetry`),
    labelled ``LABEL+se``, beside its single pass.

    Labels stay unique: a run folder or weights file whose label is taken (``runs/layer`` beside
    the shipped ``layer``) is labelled by its path as given; only a label still taken gets a
    ``-N`` suffix, and every relabelling is said in ``notes``."""
    from mcdenoise.models.inference import resolve_precision
    from mcdenoise.models.weights import load_denoiser

    methods: list[Method] = [NoisyMethod()]
    if oidn:
        from mcdenoise.eval.oidn import OIDNError, _pyoidn, parse_quality

        for q in oidn:
            try:
                parse_quality(q)
            except OIDNError as e:
                raise EvalError(str(e)) from None
        _pyoidn()  # one-line OIDNError now rather than after the first image
        methods += [OIDNMethod(q, oidn_threads) for q in dict.fromkeys(oidn)]
    if classic:
        methods.append(ClassicMethod(device=device))
    taken = {m.name for m in methods}
    try:
        resolved = list(dict.fromkeys(resolve_precision(p, device) for p in precisions))
    except ValueError as e:
        raise EvalError(f"--precision: {e}") from None
    for spec in models:
        if spec == "oidn":  # the name every command accepts for OIDN 2.5.1 high
            if "oidn-high" not in taken:
                from mcdenoise.eval.oidn import _pyoidn

                _pyoidn()
                methods.append(OIDNMethod("high", oidn_threads))
                taken.add("oidn-high")
            continue
        for prec, se in [(p, se) for p in resolved for se in ((False, True) if self_ensemble else (False,))]:
            net, info = load_denoiser(spec, device=device)
            suffix = ("+bf16" if prec == "bfloat16" else "") + ("+se" if se else "")
            label = str(info.get("label") or info["name"]) + suffix
            first = label
            if label in taken and info.get("source") in ("run", "file"):
                label = str(spec).rstrip("/\\") + suffix  # the path the user typed says which one it is
            base, n = label, 2
            while label in taken:
                label, n = f"{base}-{n}", n + 1
            taken.add(label)
            if label != first and notes is not None:
                notes.append(f"{spec}: labelled {label!r} ({first!r} was taken)")
            methods.append(ModelMethod(label, net, {**info, "precision": prec}, device, precision=prec,
                                       self_ensemble=se))
    return methods
