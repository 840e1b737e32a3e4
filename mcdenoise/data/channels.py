"""The channel vocabulary: every buffer on disk and every model input is named here.

Models ask for channels by name (``"albedo"``), never by index. A channel has a fixed number of
components with fixed suffixes, which become EXR channel names (``albedo.R``, ``normal.X``...).
The renderer may register more channels at import time with :func:`register_channel`.

Per-pixel variances are not separate vocabulary entries: the variance of channel ``name`` is stored
under :func:`variance_name` (``name + "_variance"``) with the same components.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = [
    "Channel",
    "CHANNELS",
    "register_channel",
    "get_channel",
    "num_components",
    "variance_name",
    "is_variance_name",
    "base_name",
    "RADIOMETRIC",
    "exposure_power",
]

RGB = ("R", "G", "B")
XYZ = ("X", "Y", "Z")
XY = ("X", "Y")
Y1 = ("Y",)
LOBE_TYPES = ("reflection", "transmission", "diffuse", "glossy", "specular")
LOBE_VERTICES = 3


@dataclass(frozen=True)
class Channel:
    """One named buffer.

    Attributes:
        name: vocabulary name, ``[a-z0-9_]+``.
        components: suffix of each component, e.g. ``("R", "G", "B")``.
        description: what it holds, where along the path, in which space and range.
        half_ok: True when float16 cannot overflow or lose meaningful precision (values in [-1, 1]
            or [0, 1]); bright radiance, depth, positions and ids must stay float32.
        per_sample: True when the renderer records it per sample (else per pixel only).
    """

    name: str
    components: tuple[str, ...]
    description: str
    half_ok: bool = False
    per_sample: bool = True

    @property
    def size(self) -> int:
        return len(self.components)


CHANNELS: dict[str, Channel] = {}


def register_channel(channel: Channel, *, replace: bool = False) -> Channel:
    """Add ``channel`` to the vocabulary; refuses silent redefinition unless ``replace``."""
    if not channel.name.replace("_", "").isalnum() or channel.name != channel.name.lower():
        raise ValueError(f"channel name {channel.name!r}: use lower-case letters, digits and '_'")
    if channel.name.endswith("_variance"):
        raise ValueError(f"channel name {channel.name!r}: the '_variance' suffix is reserved")
    old = CHANNELS.get(channel.name)
    if old is not None and old != channel and not replace:
        raise ValueError(f"channel {channel.name!r} is already registered with another definition")
    CHANNELS[channel.name] = channel
    return channel


def get_channel(name: str) -> Channel:
    """The vocabulary entry of ``name`` (variance names resolve to their base channel)."""
    try:
        return CHANNELS[base_name(name)]
    except KeyError:
        known = ", ".join(sorted(CHANNELS))
        raise KeyError(f"unknown channel {name!r}; known channels: {known}") from None


def num_components(name: str) -> int:
    return get_channel(name).size


def variance_name(name: str) -> str:
    return f"{name}_variance"


def is_variance_name(name: str) -> bool:
    return name.endswith("_variance")


def base_name(name: str) -> str:
    return name[: -len("_variance")] if is_variance_name(name) else name


#: Channels in units of radiance: a change of exposure multiplies them (OIDN's outputs included,
#: which follow their input up to OIDN's own rounding).
RADIOMETRIC = frozenset({"radiance", "diffuse", "specular", "oidn", "oidn_pf"})


def exposure_power(name: str) -> int:
    """How ``name`` scales with exposure ``k``: ``k ** p`` (1 for radiance-like channels, 2 for their
    variances, 0 for albedo, normals, depth and every other channel)."""
    if base_name(name) not in RADIOMETRIC:
        return 0
    return 2 if is_variance_name(name) else 1


def _builtin() -> None:
    c = register_channel
    # Radiance and its split. Linear HDR, any range: always float32.
    c(Channel("radiance", RGB, "linear HDR radiance of the sample/pixel (total)"))
    c(Channel("diffuse", RGB, "radiance of paths whose first non-delta vertex scattered diffusely; diffuse + specular = radiance"))
    c(Channel("specular", RGB, "radiance of paths whose first non-delta vertex scattered glossily/specularly, plus directly seen emission"))
    # Geometry and material at the first hit (following delta bounces is NOT done here).
    c(Channel("albedo", RGB, "BSDF albedo (reflectance) at the first hit, in [0, 1]", half_ok=True))
    c(Channel("normal", XYZ, "world-space shading normal at the first hit, unit length; 0 on a miss", half_ok=True))
    c(Channel("depth", Y1, "distance from the camera to the first hit, world units; 0 on a miss"))
    # The same at the first diffuse (non-delta, non-glossy) hit, after following specular bounces.
    c(Channel("albedo_diffuse", RGB, "albedo at the first diffuse hit", half_ok=True))
    c(Channel("normal_diffuse", XYZ, "world-space shading normal at the first diffuse hit", half_ok=True))
    c(Channel("depth_diffuse", Y1, "distance along the path to the first diffuse hit, world units"))
    c(Channel("roughness", Y1, "GGX alpha at the first hit (0 for delta/smooth, 1 for diffuse)", half_ok=True))
    c(Channel("visibility", Y1, "1 when the light sample at the first diffuse hit was unoccluded, else 0", half_ok=True))
    c(Channel(
        "lobes",
        tuple(f"{t}{v}" for v in range(1, LOBE_VERTICES + 1) for t in LOBE_TYPES),
        f"booleans (reflection, transmission, diffuse, glossy, specular) of the lobe that sampling "
        f"picked at path vertices 1..{LOBE_VERTICES}; all 0 after the path ended",
        half_ok=True,
    ))
    c(Channel("path_length", Y1, "number of scattering vertices of the path (0 = missed the scene)"))
    # Sample coordinates (SBMC Appendix A).
    c(Channel("subpixel", XY, "sub-pixel position of the sample in [0, 1)^2", half_ok=True))
    c(Channel("lens", XY, "lens position in the unit disk (0 for a pinhole camera)", half_ok=True))
    c(Channel("time", Y1, "time within the shutter interval, normalised to [0, 1]", half_ok=True))
    # Sequences (per pixel).
    c(Channel("motion", XY, "screen-space motion in pixels from the previous frame to this one", per_sample=False))
    c(Channel("position", XYZ, "world-space position of the first hit", per_sample=False))
    # Derived on demand, never stored in an image folder (mcdenoise.data.oidn_input).
    c(Channel("oidn", RGB, "Open Image Denoise 2.5.1 'high' output for the same input samples (colour, albedo, "
                           "normal); computed from the other channels, cached beside a dataset", per_sample=False))
    c(Channel("oidn_pf", RGB, "Open Image Denoise 2.5.1 'high' output with the albedo and normal guides prefiltered "
                              "by OIDN 'fast' and passed as clean; derived like 'oidn'", per_sample=False))


_builtin()

#: Scene-level features stored in ``meta.json`` (not per sample): SBMC's global features.
SCENE_FEATURES = ("fov", "aperture_radius", "focus_distance", "shutter_open", "shutter_close")
