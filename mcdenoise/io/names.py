"""The one rename table between other tools' EXR channel names and our channel vocabulary.

Recognised naming schemes (``SCHEMES``):

* ``mcdenoise`` -- ours: ``<vocabulary name>.<component>`` (``radiance.R``, ``normal.X``,
  ``depth.Y``, ``radiance_variance.G``).
* ``cycles`` -- Blender Cycles multi-layer EXR with denoising data: ``<ViewLayer>.Noisy Image.R``,
  ``<ViewLayer>.Denoising Albedo.R``, ``<ViewLayer>.Denoising Normal.X``,
  ``<ViewLayer>.Denoising Depth.Z``. Any number of leading ``<prefix>.`` segments (view layer,
  render layer) is stripped before lookup. Alpha (``.A``) is dropped. The contents follow Cycles'
  conventions, not ours (camera-space normals, albedo above 1 on lights and sky, ``Combined`` as
  the colour when Blender's denoiser is off): see :mod:`mcdenoise.io.blender`.
* ``mitsuba`` -- Mitsuba 3's ``aov`` integrator with the names of its documentation examples:
  top-level ``R, G, B`` (the image), ``dd.y.T`` / ``dd.T`` / ``depth.T`` (depth),
  ``nn.X`` / ``sh_normal.X`` (shading normal), ``albedo.R``, ``pos.X`` / ``position.X``.
* ``pbrt`` -- pbrt-v4 ``GBufferFilm``: top-level ``R, G, B``, ``Albedo.R``, ``Ns.X`` (shading
  normal), ``P.X`` (position, in the film's coordinate system), ``Variance.R``. pbrt stores the
  *per-sample* variance of radiance; it becomes ``radiance_variance`` (variance of the mean) only
  when the caller passes ``spp`` (divided by it), otherwise it stays under its own name.
* ``oidn`` -- Open Image Denoise's training-file naming: one RGB file per feature, named
  ``<stem>_<spp>spp.<feature>.exr`` or ``<stem>_ref.<feature>.exr`` (feature ``hdr``, ``ldr``,
  ``alb``, ``nrm``); see :func:`parse_oidn_filename`. Top-level ``R, G, B`` of such a file take the
  feature's vocabulary name (``nrm`` components map R, G, B -> X, Y, Z).

Layers whose names are not recognised are returned under their own (EXR) layer name. Alpha
(``A``) of a recognised layer is dropped; other components a table entry does not claim stay under
the EXR layer name (``"image"`` for top-level channels).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from mcdenoise.data.channels import CHANNELS, base_name, get_channel

__all__ = [
    "SCHEMES",
    "Rename",
    "RENAMES",
    "OIDN_FEATURES",
    "lookup_layer",
    "split_channel",
    "group_channels",
    "to_exr_channel_names",
    "parse_oidn_filename",
    "oidn_filename",
    "component_suffixes",
]

SCHEMES = ("mcdenoise", "cycles", "mitsuba", "pbrt", "oidn")


@dataclass(frozen=True)
class Rename:
    """How one external layer maps onto a vocabulary channel.

    Attributes:
        scheme: which tool writes this name.
        layer: the external layer name (after stripping Cycles-style prefixes); ``""`` = top level.
        channel: vocabulary name (or ``*_variance``) it becomes.
        components: external component suffix -> our component suffix; others are dropped.
        per_sample_variance: the external values are the per-sample variance; divide by spp to
            get our variance of the mean.
    """

    scheme: str
    layer: str
    channel: str
    components: tuple[tuple[str, str], ...]
    per_sample_variance: bool = False


_RGB = (("R", "R"), ("G", "G"), ("B", "B"))
_XYZ = (("X", "X"), ("Y", "Y"), ("Z", "Z"))
_RGB_AS_XYZ = (("R", "X"), ("G", "Y"), ("B", "Z"))

#: The rename table. Order matters only for writing: the first entry of a scheme that produces
#: a channel is the name we write for it.
RENAMES: tuple[Rename, ...] = (
    # Blender Cycles (denoising data passes).
    Rename("cycles", "Noisy Image", "radiance", _RGB),
    Rename("cycles", "Denoising Albedo", "albedo", _RGB),
    Rename("cycles", "Denoising Normal", "normal", _XYZ),
    # A render writes depth's one channel as Z; Blender 5's File Output node writes a value as V.
    Rename("cycles", "Denoising Depth", "depth", (("Z", "Y"), ("V", "Y"))),
    # Mitsuba 3 aov integrator (names from its documentation).
    Rename("mitsuba", "", "radiance", _RGB),
    Rename("mitsuba", "dd.y", "depth", (("T", "Y"),)),
    Rename("mitsuba", "dd", "depth", (("T", "Y"),)),
    Rename("mitsuba", "depth", "depth", (("T", "Y"),)),
    Rename("mitsuba", "nn", "normal", _XYZ),
    Rename("mitsuba", "sh_normal", "normal", _XYZ),
    Rename("mitsuba", "albedo", "albedo", _RGB),
    Rename("mitsuba", "pos", "position", _XYZ),
    Rename("mitsuba", "position", "position", _XYZ),
    # pbrt-v4 GBufferFilm.
    Rename("pbrt", "", "radiance", _RGB),
    Rename("pbrt", "Albedo", "albedo", _RGB),
    Rename("pbrt", "Ns", "normal", _XYZ),
    Rename("pbrt", "P", "position", _XYZ),
    Rename("pbrt", "Variance", "radiance_variance", _RGB, per_sample_variance=True),
)

#: OIDN file feature suffix -> (vocabulary channel, component map).
OIDN_FEATURES: dict[str, tuple[str, tuple[tuple[str, str], ...]]] = {
    "hdr": ("radiance", _RGB),
    "ldr": ("radiance", _RGB),
    "alb": ("albedo", _RGB),
    "nrm": ("normal", _RGB_AS_XYZ),
}

_OIDN_RE = re.compile(r"^(?P<stem>.+?)_(?:(?P<spp>\d+)spp|(?P<ref>ref))\.(?P<feature>[a-z]+)\.exr$")
_TOP_ORDER = ("R", "G", "B", "A", "X", "Y", "Z", "T", "U", "V", "W")


def split_channel(name: str) -> tuple[str, str]:
    """``"view.Noisy Image.R"`` -> ``("view.Noisy Image", "R")``; ``"R"`` -> ``("", "R")``."""
    layer, dot, comp = name.rpartition(".")
    return (layer, comp) if dot else ("", name)


def _is_vocabulary(layer: str) -> bool:
    return base_name(layer) in CHANNELS


def lookup_layer(layer: str, *, filename: str | None = None) -> Rename | None:
    """The rename entry for an external layer name, or None when it is ours or unknown.

    Cycles-style prefixes (``ViewLayer.``) are stripped one segment at a time until a table entry
    matches. For top-level channels of an OIDN-named file the feature in ``filename`` decides.
    """
    if layer == "" and filename is not None:
        parsed = parse_oidn_filename(filename)
        if parsed is not None and parsed[2] in OIDN_FEATURES:
            chan, comps = OIDN_FEATURES[parsed[2]]
            return Rename("oidn", "", chan, comps)
    if _is_vocabulary(layer):
        return None
    candidate = layer
    while True:
        for r in RENAMES:
            if r.layer == candidate:
                return r
        if "." not in candidate:
            return None
        candidate = candidate.split(".", 1)[1]


def component_suffixes(layer: str, count: int) -> tuple[str, ...]:
    """EXR component suffixes for ``layer``: from the vocabulary, else a generic guess."""
    if _is_vocabulary(layer):
        comps = get_channel(layer).components
        if len(comps) != count:
            raise ValueError(f"layer {layer!r} has {count} components; the vocabulary says {len(comps)}")
        return comps
    generic = {1: ("Y",), 2: ("X", "Y"), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}
    return generic.get(count, tuple(str(i) for i in range(count)))


def group_channels(
    channel_names: list[str], *, filename: str | None = None, spp: int | None = None
) -> dict[str, tuple[list[tuple[str, str]], float]]:
    """Group EXR channel names into our layers.

    Returns ``layer -> ([(exr channel, our component), ...] in our component order, scale)``;
    ``scale`` multiplies the values (``1/spp`` for per-sample variances, else 1).
    """
    from mcdenoise.io.blender import view_layer

    out: dict[str, tuple[list[tuple[str, str]], float]] = {}
    by_layer: dict[str, list[str]] = {}
    for name in channel_names:
        layer, comp = split_channel(name)
        by_layer.setdefault(layer, []).append(comp)
    # A Cycles file with several view layers is read from one (io/blender.py view_layer): the
    # passes of the others keep their own names rather than lend a guide to another layer's colour.
    cycles_prefix = view_layer(list(channel_names))
    for layer, comps in by_layer.items():
        rename = lookup_layer(layer, filename=filename)
        if rename is not None and rename.per_sample_variance and spp is None:
            rename = None  # cannot convert without spp: keep it under its own name
        if (rename is not None and rename.scheme == "cycles" and cycles_prefix is not None
                and layer[: len(layer) - len(rename.layer)] != cycles_prefix):
            rename = None  # another view layer's pass
        if rename is not None:
            cmap = dict(rename.components)
            target = rename.channel
            order = get_channel(target).components
            pairs = [(f"{layer}.{c}" if layer else c, cmap[c]) for c in comps if c in cmap]
            pairs.sort(key=lambda p: order.index(p[1]))
            scale = 1.0 / spp if (rename.per_sample_variance and spp) else 1.0
            # First source wins (e.g. two view layers). An entry that claims none of the layer's
            # components (a lone top-level "Z" or "Y": a depth file) is no source at all.
            if target not in out and pairs:
                out[target] = (pairs, scale)
            # Components the entry does not claim (pbrt's top-level u, v...) are kept; alpha is not.
            comps = [c for c in comps if c not in cmap and c != "A"]
            if not comps:
                continue
        target = layer if layer else "image"
        if _is_vocabulary(layer):
            order = get_channel(layer).components
            pairs = [(f"{layer}.{c}", c) for c in comps if c in order]
            pairs.sort(key=lambda p: order.index(p[1]))
        else:
            rank = {c: i for i, c in enumerate(_TOP_ORDER)}
            ordered = sorted(comps, key=lambda c: (rank.get(c, len(rank)), c))
            pairs = [(f"{layer}.{c}" if layer else c, c) for c in ordered]
        out[target] = (pairs, 1.0)
    return out


def to_exr_channel_names(layer: str, count: int, scheme: str = "mcdenoise", *, view_layer: str = "ViewLayer") -> list[str]:
    """EXR channel names for our ``layer`` with ``count`` components, written in ``scheme``.

    Raises KeyError when the scheme has no name for the layer. For ``oidn`` the names are the
    top-level ``R, G, B`` of the per-feature file (see :func:`oidn_filename`).
    """
    if scheme not in SCHEMES:
        raise KeyError(f"unknown naming scheme {scheme!r}; known: {SCHEMES}")
    comps = component_suffixes(layer, count)
    if scheme == "mcdenoise":
        return [f"{layer}.{c}" for c in comps]
    if scheme == "oidn":
        for chan, cmap in OIDN_FEATURES.values():
            if chan == layer:
                inv = {ours: theirs for theirs, ours in cmap}
                return [inv[c] for c in comps]
        raise KeyError(f"OIDN naming has no file for channel {layer!r}")
    for r in RENAMES:
        if r.scheme == scheme and r.channel == layer and not r.per_sample_variance:
            inv = {ours: theirs for theirs, ours in r.components}
            prefix = f"{view_layer}.{r.layer}." if scheme == "cycles" else (f"{r.layer}." if r.layer else "")
            return [prefix + inv[c] for c in comps]
    raise KeyError(f"naming scheme {scheme!r} has no name for channel {layer!r}")


def parse_oidn_filename(name: str | Path) -> tuple[str, int | None, str] | None:
    """OIDN's naming rule: ``<stem>_<N>spp.<feature>.exr`` -> ``(stem, N, feature)``;
    ``<stem>_ref.<feature>.exr`` -> ``(stem, None, feature)``; anything else -> None."""
    m = _OIDN_RE.match(Path(name).name)
    if m is None:
        return None
    spp = int(m.group("spp")) if m.group("spp") is not None else None
    return m.group("stem"), spp, m.group("feature")


def oidn_filename(stem: str, channel: str, spp: int | None) -> str:
    """The OIDN file name for ``channel`` (radiance -> ``hdr``); ``spp=None`` for the reference."""
    for feature, (chan, _) in OIDN_FEATURES.items():
        if chan == channel and feature != "ldr":
            tag = "ref" if spp is None else f"{spp:04d}spp"
            return f"{stem}_{tag}.{feature}.exr"
    raise KeyError(f"OIDN naming has no file for channel {channel!r}")

