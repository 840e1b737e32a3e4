"""Render per-sample data and references with Mitsuba 3.

The per-sample path generates all ``W*H*S`` camera rays itself and consumes the sampler in the
order ``mi.render`` does (sub-pixel 2D, aperture 2D when the sensor has a lens, time 1D when it has
a shutter, then the integrator), so the per-pixel mean of the samples equals ``mi.render`` with a
box filter and our ``mcdenoise_path`` integrator at the same seed and spp, whenever the image fits
in one chunk (:attr:`RenderSettings.chunk_samples`). Larger images are rendered in row bands with
seeds derived per band (still unbiased, no longer identical to one ``mi.render`` call).

Distributed effects:

* depth of field: any Mitsuba ``thinlens`` sensor; the lens position is recorded per sample.
* camera motion: ``camera_to_world_end``; every ray is moved to its own time (exact per sample).
* object motion: ``object_motion`` (shape id -> translation over the shutter). Mitsuba 3 has no
  moving shapes, so sample index ``s`` of every pixel is rendered with the scene posed at one
  stratified time ``(s + u_s) / S`` (``u_s`` from the seed): one time slice per sample index.

Seeds, times and sizes reach the kernels as opaque values, so a new seed or time never recompiles.
"""

from __future__ import annotations

import json
import os
import re
import sys
import time as _time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Collection, Iterator, Mapping, Sequence

import numpy as np
from tqdm import tqdm

from mcdenoise.data.channels import SCENE_FEATURES
from mcdenoise.errors import SceneError
from mcdenoise.render._mitsuba import mitsuba
from mcdenoise.render.integrator import (
    FULL_OUTPUTS,
    INTEGRATOR_NAME,
    LEVEL_FULL,
    LEVEL_REFERENCE,
)
from mcdenoise.render.scenes import BUILTIN_SCENES

__all__ = [
    "RenderSettings",
    "SAMPLE_CHANNELS",
    "REFERENCE_CHANNELS",
    "list_builtin_scenes",
    "builtin_motion",
    "load_scene",
    "scene_features",
    "render_samples",
    "iter_sample_chunks",
    "render_reference",
    "render_image",
    "derive_seed",
]

#: Per-sample channels the renderer can record, in the order it writes them.
SAMPLE_CHANNELS: tuple[str, ...] = (
    "radiance",
    "diffuse",
    "specular",
    "albedo",
    "normal",
    "depth",
    "albedo_diffuse",
    "normal_diffuse",
    "depth_diffuse",
    "roughness",
    "visibility",
    "lobes",
    "path_length",
    "subpixel",
    "lens",
    "time",
)
#: Channels of the reference image.
REFERENCE_CHANNELS: tuple[str, ...] = ("radiance", "diffuse", "specular", "albedo")

MAX_SIZE = 16384
MAX_SPP = 1 << 20


@dataclass
class RenderSettings:
    """How to render one image.

    Attributes:
        spp: samples per pixel of the per-sample (noisy) input.
        ref_spp: samples per pixel of the reference (0 = no reference).
        width, height: image size in pixels (overrides the scene's film).
        seed: base seed; the reference uses seeds derived from it, independent of the input's.
        max_depth: Mitsuba's convention (1 = emitters seen directly, 2 = direct lighting, ...);
            used by input and reference alike.
        channels: per-sample channels to record (None = all of SAMPLE_CHANNELS; ``radiance`` is
            always recorded).
        rr_depth: depth at which Russian roulette starts (Mitsuba's default 5).
        object_motion: shape id -> world translation over the shutter (object motion blur).
        camera_to_world_end: 4x4 camera-to-world at shutter close (camera motion blur).
        chunk_samples: samples traced per kernel launch (bounds memory, ~200 bytes per sample).
        ref_time_slices: most time slices of the reference when objects move (each slice is a
            scene update and a kernel launch, ~30-90 ms on 2 cores; the procedural dataset
            lowers it to what the on-screen motion needs).
    """

    spp: int = 8
    ref_spp: int = 4096
    width: int = 256
    height: int = 256
    seed: int = 0
    max_depth: int = 6
    channels: tuple[str, ...] | None = None
    rr_depth: int = 5
    object_motion: dict[str, tuple[float, float, float]] | None = None
    camera_to_world_end: Any = None
    chunk_samples: int = 1 << 21
    ref_time_slices: int = 256

    def check(self) -> None:
        """Raise SceneError on absurd values."""
        for name, v, lo, hi in (
            ("width", self.width, 1, MAX_SIZE),
            ("height", self.height, 1, MAX_SIZE),
            ("spp", self.spp, 1, MAX_SPP),
            ("ref_spp", self.ref_spp, 0, MAX_SPP),
            ("max_depth", self.max_depth, 1, 1024),
            ("chunk_samples", self.chunk_samples, 1, 1 << 31),
            ("ref_time_slices", self.ref_time_slices, 1, 1 << 20),
        ):
            if not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise SceneError(f"render settings: {name}={v!r} is out of range [{lo}, {hi}]")
        if self.channels is not None:
            bad = [c for c in self.channels if c not in SAMPLE_CHANNELS and c != "position"]
            if bad:
                raise SceneError(f"render settings: unknown per-sample channels {bad}; known: {list(SAMPLE_CHANNELS)}")

    def sample_channels(self) -> tuple[str, ...]:
        if self.channels is None:
            return SAMPLE_CHANNELS
        want = set(self.channels) | {"radiance"}
        return tuple(c for c in SAMPLE_CHANNELS if c in want)


def derive_seed(seed: int, *keys: int) -> int:
    """A 32-bit seed derived from ``seed`` and ``keys`` (independent streams per key tuple)."""
    ss = np.random.SeedSequence([int(seed) & 0xFFFFFFFF, 0x6D63646E, *[int(k) & 0xFFFFFFFF for k in keys]])
    return int(ss.generate_state(1, dtype=np.uint32)[0])


def list_builtin_scenes() -> dict[str, str]:
    """Built-in scene name -> one-line description."""
    return {name: s.description for name, s in BUILTIN_SCENES.items()}


def builtin_motion(name: str) -> dict[str, Any]:
    """RenderSettings fields (object_motion, camera_to_world_end) a built-in scene carries."""
    s = BUILTIN_SCENES[name]
    out: dict[str, Any] = {}
    if s.object_motion:
        out["object_motion"] = dict(s.object_motion)
    if s.camera_to_world_end is not None:
        out["camera_to_world_end"] = np.asarray(s.camera_to_world_end, dtype=np.float64)
    return out


def _first_line(e: BaseException) -> str:
    text = str(e).strip()
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    # Mitsuba prefixes errors with "[xml.cpp:...] Error while loading ...": keep the informative tail.
    msg = lines[-1] if lines else type(e).__name__
    if any("unused parameter" in ln.lower() for ln in lines):
        # Mitsuba lists them one per line after the header; a -D the scene does not use.
        names = [ln.lstrip("- ") for ln in lines if ln.startswith("- ")]
        return f"the scene uses no parameter {', '.join(names)} (check the -D names)"[:400]
    for ln in lines:
        if "unknown" in ln.lower() or "not found" in ln.lower() or "could not" in ln.lower():
            msg = ln
            break
    return msg[:400]


#: Mitsuba 3 sensor plugins, to find the sensor entry of a scene dict.
_SENSOR_TYPES = frozenset({"perspective", "thinlens", "orthographic", "radiancemeter", "irradiancemeter", "distant", "batch"})
#: Film parameters of a crop window (Mitsuba 3 names, and Mitsuba 0.6 names that its upgrade renames).
_CROP_PARAMS = frozenset({"crop_offset_x", "crop_offset_y", "crop_width", "crop_height",
                          "cropoffsetx", "cropoffsety", "cropwidth", "cropheight"})


def _crop_refusal(where: str, names: Collection[str]) -> SceneError:
    return SceneError(
        f"{where}: the film has a crop window ({', '.join(sorted(names))}); a new image size would change "
        "which part of the image it selects: remove the crop window from the scene, or render at the "
        "film's own size (no --size / width / height)"
    )


def _xml_with_film_size(path: Path, width: int | None, height: int | None) -> tuple[str, set[str]]:
    """The scene file's text with the first sensor's film set to ``width`` x ``height``, and the
    names of the ``$parameters`` the replaced width/height values referred to.

    Mitsuba derives a camera's projection (its x field of view from ``fov_axis`` or
    ``focal_length``, the thin lens, the orthographic extent) from the film size while it builds
    the sensor; resizing the film of a loaded scene keeps the old projection. So the size is
    written into the scene description before Mitsuba instantiates anything.
    """
    import xml.etree.ElementTree as ET

    where = str(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise SceneError(f"{where}: not a valid XML file ({e})") from None
    # Document order, as Mitsuba lists the sensors: scene.sensors()[0] is the first <sensor>.
    sensor = next(root.iter("sensor"), None)
    if sensor is None:
        raise SceneError(
            f"{where}: no <sensor> in this file (one in an <include>d file cannot be resized): "
            "set the film size in the file or leave out --size / width / height"
        )
    film = sensor.find("film")
    if film is None:
        # Mitsuba's default film when a sensor names none.
        film = ET.SubElement(sensor, "film", {"type": "hdrfilm"})
    crop = {c.get("name", "") for c in film if c.get("name", "").lower() in _CROP_PARAMS}
    if crop:
        raise _crop_refusal(where, crop)
    replaced: set[str] = set()
    for name, value in (("width", width), ("height", height)):
        if value is None:
            continue
        for child in [c for c in film if c.get("name") == name]:
            replaced.update(re.findall(r"\$([A-Za-z0-9_]+)", child.get("value", "")))
            film.remove(child)
        ET.SubElement(film, "integer", {"name": name, "value": str(int(value))})
    return ET.tostring(root, encoding="unicode"), replaced


def _dict_with_film_size(scene: dict, width: int | None, height: int | None) -> dict:
    """A shallow copy of a scene dict whose first sensor's film is ``width`` x ``height`` (see
    :func:`_xml_with_film_size` for why the size goes in before loading)."""
    key = next((k for k, v in scene.items() if isinstance(v, dict) and v.get("type") in _SENSOR_TYPES), None)
    if key is None:
        raise SceneError("<scene dict>: no sensor entry (type perspective, thinlens, orthographic, ...) to resize")
    sensor = dict(scene[key])
    film = dict(sensor.get("film", {"type": "hdrfilm"}))
    crop = {k for k in film if k.lower() in _CROP_PARAMS}
    if crop:
        raise _crop_refusal("<scene dict>", crop)
    if width is not None:
        film["width"] = int(width)
    if height is not None:
        film["height"] = int(height)
    sensor["film"] = film
    return {**scene, key: sensor}


def _film_size(scene: Any) -> tuple[int, int]:
    """(width, height) of the image the scene's first sensor renders: its film's crop window."""
    size = scene.sensors()[0].film().crop_size()
    return int(size[0]), int(size[1])


def load_scene(
    scene: str | os.PathLike | dict,
    *,
    defines: dict[str, str] | None = None,
    width: int | None = None,
    height: int | None = None,
) -> Any:
    """Load a Mitsuba 3 scene: an XML file (0.6 files are upgraded), a built-in name, or a dict.

    ``defines`` set ``$name`` defaults of a file like Mitsuba's ``-D``. ``width``/``height``
    set the film size before the scene is instantiated, so the camera is exactly the one Mitsuba
    builds for a film of that size (field of view, lens, orthographic extent); a film with a crop
    window is refused then. Without them the film's own size (its crop window, if any) is kept.
    Raises SceneError on any problem (missing file, unknown plugin, no sensor, absurd size).
    """
    mi = mitsuba()
    for n, v in (("width", width), ("height", height)):
        if v is not None and not 1 <= int(v) <= MAX_SIZE:
            raise SceneError(f"{scene if not isinstance(scene, dict) else '<dict>'}: {n}={v} is out of range [1, {MAX_SIZE}]")
    resize = width is not None or height is not None
    if isinstance(scene, dict):
        where = "<scene dict>"
        d = _dict_with_film_size(scene, width, height) if resize else scene
        try:
            loaded = mi.load_dict(d)
        except Exception as e:  # noqa: BLE001 - Mitsuba raises RuntimeError/TypeError with its text
            raise SceneError(f"{where}: {_first_line(e)}") from None
    elif isinstance(scene, str) and scene in BUILTIN_SCENES:
        where = f"built-in scene {scene!r}"
        d = BUILTIN_SCENES[scene].build(mi, int(width or 256), int(height or 256))
        try:
            loaded = mi.load_dict(d)
        except Exception as e:  # noqa: BLE001
            raise SceneError(f"{where}: {_first_line(e)}") from None
    else:
        path = Path(scene)
        where = str(path)
        if not path.exists():
            known = ", ".join(BUILTIN_SCENES)
            raise SceneError(f"{where}: no such scene file (built-in scenes: {known})")
        if path.is_dir():
            raise SceneError(f"{where}: is a folder, not a scene file")
        kwargs = {str(k): str(v) for k, v in (defines or {}).items()}
        try:
            if not resize:
                loaded = mi.load_file(str(path), **kwargs)
            else:
                text, replaced = _xml_with_film_size(path, width, height)
                # Mitsuba refuses a -D value that nothing uses; one that only set the film size
                # (e.g. -D res=...) is overridden by the explicit size instead.
                for name in replaced:
                    if name in kwargs and not re.search(rf"\${name}(?![A-Za-z0-9_])", text):
                        del kwargs[name]
                # load_file resolves relative paths (meshes, textures, includes) against the
                # file's folder; a string has no folder, so lend it that one while it loads.
                saved = mi.FileResolver(mi.file_resolver())
                resolver = mi.FileResolver(saved)
                resolver.prepend(str(path.resolve().parent))
                mi.set_file_resolver(resolver)
                try:
                    loaded = mi.load_string(text, **kwargs)
                finally:
                    mi.set_file_resolver(saved)
        except SceneError:
            raise
        except Exception as e:  # noqa: BLE001
            raise SceneError(f"{where}: {_first_line(e)}") from None
    if loaded is None or len(loaded.sensors()) == 0:
        raise SceneError(f"{where}: the scene has no sensor (camera)")
    got = _film_size(loaded)
    want = (got[0] if width is None else int(width), got[1] if height is None else int(height))
    if got != want:
        raise SceneError(f"{where}: asked for a {want[0]}x{want[1]} film but the first sensor has {got[0]}x{got[1]}")
    return loaded


def _sensor_params(sensor: Any) -> dict[str, float]:
    mi = mitsuba()
    params = mi.traverse(sensor)
    keys = set(params.keys())

    def scalar(key: str, default: float) -> float:
        if key not in keys:
            return default
        return float(np.asarray(params[key]).reshape(-1)[0])

    return {
        "fov": scalar("x_fov", 0.0),
        "aperture_radius": scalar("aperture_radius", 0.0),
        "focus_distance": scalar("focus_distance", 0.0),
        "shutter_open": float(sensor.shutter_open()),
        "shutter_close": float(sensor.shutter_open() + sensor.shutter_open_time()),
    }


def scene_features(scene: Any) -> dict[str, float]:
    """SBMC's global features of the scene's first sensor (keys: channels.SCENE_FEATURES)."""
    p = _sensor_params(scene.sensors()[0])
    return {k: p[k] for k in SCENE_FEATURES}


# --------------------------------------------------------------------------------------------
# Internals


def _bsdf_alpha(bsdf: Any) -> float:
    """GGX alpha of a BSDF for the ``roughness`` channel: its alpha/roughness parameter (texture
    mean), 1 for purely diffuse materials, 0 for smooth (delta) ones."""
    mi = mitsuba()
    flags = int(bsdf.flags())
    params = mi.traverse(bsdf)
    alphas: list[float] = []
    for key in params.keys():
        parts = [p for p in key.split(".") if p not in ("value", "data")]
        if not parts:
            continue
        leaf = parts[-1]
        if leaf in ("alpha", "alpha_u", "alpha_v", "roughness"):
            try:
                v = float(np.mean(np.asarray(params[key], dtype=np.float64)))
            except (TypeError, ValueError):
                continue
            alphas.append(v * v if leaf == "roughness" else v)
    if alphas:
        return float(np.clip(np.mean(alphas), 0.0, 1.0))
    if flags & int(mi.BSDFFlags.Glossy):
        return 0.5
    if flags & int(mi.BSDFFlags.Diffuse):
        return 1.0
    return 0.0


def _roughness_table(scene: Any) -> Any:
    mi = mitsuba()
    import drjit as dr

    entries: dict[int, float] = {}
    for shape in scene.shapes():
        b = shape.bsdf()
        if b is None:
            continue
        rid = int(dr.reinterpret_array(mi.UInt32, mi.BSDFPtr(b))[0])
        if rid not in entries:
            entries[rid] = _bsdf_alpha(b)
    size = max(entries, default=0) + 1
    table = np.zeros(size, dtype=np.float32)
    for rid, a in entries.items():
        table[rid] = a
    return mi.Float(table)


@dataclass
class _Prepared:
    """Per-call state: integrator, sensor, motion bookkeeping."""

    integrator: Any
    sensor: Any
    width: int
    height: int
    has_lens: bool
    shutter_open: float
    shutter_time: float
    cam_start: np.ndarray | None = None
    cam_end: np.ndarray | None = None
    # param key (to_world or vertex_positions) -> (base value as float64 array, translation)
    motion: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    # vertex_positions key -> (its vertex_normals key, normals as loaded (float32, flat))
    normals: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)
    params: Any = None
    restore_camera: Any = None


def _prepare(scene: Any, settings: RenderSettings, camera_to_world: np.ndarray | None) -> _Prepared:
    mi = mitsuba()
    settings.check()
    film = _film_size(scene)
    if film != (settings.width, settings.height):
        # Resizing a loaded film keeps the projection built for the old size (see load_scene).
        raise SceneError(
            f"render settings: {settings.width}x{settings.height} but the scene's film is {film[0]}x{film[1]}: "
            "load the scene at the size to render (load_scene(..., width=, height=))"
        )
    integrator = mi.load_dict({"type": INTEGRATOR_NAME, "max_depth": int(settings.max_depth), "rr_depth": int(settings.rr_depth)})
    integrator.roughness_table = _roughness_table(scene)
    sensor = scene.sensors()[0]
    prep = _Prepared(
        integrator=integrator,
        sensor=sensor,
        width=settings.width,
        height=settings.height,
        has_lens=bool(sensor.needs_aperture_sample()),
        shutter_open=float(sensor.shutter_open()),
        shutter_time=float(sensor.shutter_open_time()),
    )
    sparams = mi.traverse(sensor)
    if camera_to_world is not None:
        m = np.asarray(camera_to_world, dtype=np.float64)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise SceneError(f"camera_to_world: expected a finite 4x4 matrix, got shape {m.shape}")
        prep.restore_camera = mi.Transform4f(sparams["to_world"])
        sparams["to_world"] = mi.Transform4f(m.tolist())
        sparams.update()
    if settings.camera_to_world_end is not None:
        end = np.asarray(settings.camera_to_world_end, dtype=np.float64)
        if end.shape != (4, 4) or not np.all(np.isfinite(end)):
            raise SceneError(f"camera_to_world_end: expected a finite 4x4 matrix, got shape {end.shape}")
        if prep.shutter_time <= 0:
            raise SceneError("camera motion needs a sensor with a shutter (shutter_close > shutter_open)")
        start = np.array(mi.Transform4f(sparams["to_world"]).matrix, dtype=np.float64).reshape(4, 4)
        prep.cam_start, prep.cam_end = start, end
    if settings.object_motion:
        params = mi.traverse(scene)
        keys = set(params.keys())
        for shape_id, tr in settings.object_motion.items():
            tr = np.asarray(tr, dtype=np.float64).reshape(3)
            key = f"{shape_id}.to_world"
            vkey = f"{shape_id}.vertex_positions"
            if key in keys:
                m = np.array(mi.Transform4f(params[key]).matrix, dtype=np.float64).reshape(4, 4)
                prep.motion[key] = (m, tr)
            elif vkey in keys:
                # Meshes without a to_world parameter (cube, obj, ply): move the vertices.
                prep.motion[vkey] = (np.array(params[vkey], dtype=np.float64).reshape(-1, 3), tr)
                nkey = f"{shape_id}.vertex_normals"
                if nkey in keys:
                    normals = np.array(params[nkey], dtype=np.float32).reshape(-1)
                    if normals.size:
                        prep.normals[vkey] = (nkey, normals)
            else:
                movable = sorted({k.rsplit(".", 1)[0] for k in keys if k.endswith((".to_world", ".vertex_positions"))} - {"sensor"})
                raise SceneError(f"object_motion: no movable shape with id {shape_id!r} (movable shapes: {movable})")
        prep.params = params
    return prep


def _restore(scene: Any, prep: _Prepared) -> None:
    mi = mitsuba()
    if prep.motion:
        _pose_objects(prep, 0.0)
    if prep.restore_camera is not None:
        sp = mi.traverse(prep.sensor)
        sp["to_world"] = prep.restore_camera
        sp.update()


def _pose_objects(prep: _Prepared, t: float) -> None:
    """Move every animated shape to normalised shutter time ``t`` (0 = the scene as loaded)."""
    mi = mitsuba()
    for key, (base, tr) in prep.motion.items():
        if key.endswith(".to_world"):
            m = base.copy()
            m[:3, 3] += tr * t
            prep.params[key] = mi.Transform4f(m.tolist())
        else:
            prep.params[key] = mi.Float((base + tr * t).astype(np.float32).reshape(-1))
            if key in prep.normals:
                # New vertex positions alone make Mitsuba recompute the vertex normals from the
                # faces: a moved mesh then shades with other normals than the loaded one (0.12
                # apart on a procedural mesh), and the recomputation sums with atomics, so
                # reference renders differed run to run (~1e-6). A translation keeps the
                # normals: hand the loaded ones back (a fresh array, else the update skips it).
                nkey, normals = prep.normals[key]
                prep.params[nkey] = mi.Float(normals)
    prep.params.update()


def _rotation_parts(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """Split an affine camera transform into a proper rotation, translation and a mirror flag."""
    r = m[:3, :3].copy()
    flip = np.linalg.det(r) < 0
    if flip:
        r[:, 0] = -r[:, 0]
    # Remove any scale so the quaternion is well defined.
    u, _, vt = np.linalg.svd(r)
    return u @ vt, m[:3, 3].copy(), bool(flip)


def _quat(r: np.ndarray) -> np.ndarray:
    """Quaternion (x, y, z, w) of a rotation matrix."""
    tr = np.trace(r)
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k]) * 2
        q = [0.0, 0.0, 0.0, 0.0]
        q[i] = 0.25 * s
        q[j] = (r[j, i] + r[i, j]) / s
        q[k] = (r[k, i] + r[i, k]) / s
        q[3] = (r[k, j] - r[j, k]) / s
    return np.asarray(q, dtype=np.float64)


def _move_camera_rays(ray: Any, t: Any, prep: _Prepared) -> Any:
    """Re-pose rays generated at the start transform to the camera at normalised time ``t``."""
    mi = mitsuba()
    import drjit as dr

    r0, p0, flip0 = _rotation_parts(prep.cam_start)
    r1, p1, flip1 = _rotation_parts(prep.cam_end)
    if flip0 != flip1:
        raise SceneError("camera motion: start and end transforms differ in handedness")
    q0, q1 = _quat(r0), _quat(r1)
    if np.dot(q0, q1) < 0:
        q1 = -q1
    inv_start = mi.Transform4f(np.linalg.inv(prep.cam_start).tolist())
    # Per-lane normalised-lerp of the rotation (nlerp is within 0.1% of slerp for the small
    # turns of a shutter interval and is cheap), lerp of the translation.
    q = [mi.Float(float(a)) * (1.0 - t) + float(b) * t for a, b in zip(q0, q1)]
    n = dr.rsqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    x, y, z, w = (c * n for c in q)
    rot = mi.Matrix3f(
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    )
    trans = mi.Vector3f(*[float(a) for a in p0]) * (1.0 - t) + mi.Vector3f(*[float(b) for b in p1]) * t
    sign = mi.Vector3f(-1.0 if flip0 else 1.0, 1.0, 1.0)

    def point(p: Any) -> Any:
        local = inv_start @ mi.Point3f(p)
        return mi.Point3f(rot @ (mi.Vector3f(local) * sign) + trans)

    def vector(v: Any) -> Any:
        local = inv_start @ mi.Vector3f(v)
        return dr.normalize(rot @ (mi.Vector3f(local) * sign))

    ray.o = point(ray.o)
    ray.d = vector(ray.d)
    if ray.has_differentials:
        ray.o_x, ray.o_y = point(ray.o_x), point(ray.o_y)
        ray.d_x, ray.d_y = vector(ray.d_x), vector(ray.d_y)
    return ray


def _trace_chunk(
    scene: Any,
    prep: _Prepared,
    *,
    rows: slice,
    spp: int,
    seed: int,
    level: int,
    time_override: float | None,
    record_position: bool,
    reduce: bool,
    keep: Collection[str] | None = None,
) -> dict[str, np.ndarray]:
    """Trace rows ``rows`` at ``spp`` samples per pixel.

    Returns name -> (spp, C, h, W) float32 per-sample arrays, or (C, h, W) float64 pixel sums when
    ``reduce``. ``keep`` (None = all) limits the outputs; the kernel then skips the others.
    """
    mi = mitsuba()
    import drjit as dr

    W = prep.width
    y0, y1 = rows.start, rows.stop
    h = y1 - y0
    n = W * h * spp
    sampler = prep.sensor.sampler().fork()
    sampler.set_sample_count(spp)
    sampler.set_samples_per_wavefront(spp)
    sampler.seed(dr.opaque(mi.UInt32, seed & 0xFFFFFFFF), n)

    idx = dr.arange(mi.UInt32, n)
    idx //= dr.opaque(mi.UInt32, spp)
    py = idx // dr.opaque(mi.UInt32, W)
    px = idx - py * dr.opaque(mi.UInt32, W)
    py += dr.opaque(mi.UInt32, y0)
    pos = mi.Vector2f(mi.Float(px), mi.Float(py))
    sub = sampler.next_2d()
    sample_pos = pos + sub
    scale = mi.ScalarVector2f(1.0 / W, 1.0 / prep.height)
    adjusted = dr.fma(sample_pos, scale, mi.ScalarVector2f(0.0, 0.0))
    aperture = mi.Point2f(0.5)
    if prep.has_lens:
        aperture = sampler.next_2d()
    t_ray = mi.Float(prep.shutter_open)
    t_norm = mi.Float(0.0)
    if prep.shutter_time > 0:
        u = sampler.next_1d()
        if time_override is not None:
            u = dr.opaque(mi.Float, float(time_override)) + 0.0 * u
        t_ray = t_ray + u * prep.shutter_time
        t_norm = u
    elif time_override is not None:
        t_norm = dr.opaque(mi.Float, float(time_override)) + mi.Float(0.0) * sub.x
    ray, ray_weight = prep.sensor.sample_ray_differential(t_ray, 0.0, adjusted, aperture)
    if ray.has_differentials:
        ray.scale_differential(dr.rsqrt(float(spp)))
    if prep.cam_start is not None:
        ray = _move_camera_rays(ray, t_norm, prep)
    out = prep.integrator.trace(scene, sampler, ray, mi.Bool(True), level)
    values: dict[str, Any] = {"radiance": ray_weight * out["radiance"]}
    if level >= LEVEL_REFERENCE:
        values["diffuse"] = ray_weight * out["diffuse"]
        values["specular"] = ray_weight * out["specular"]
        values["albedo"] = out["albedo"]
    if level >= LEVEL_FULL:
        for k in FULL_OUTPUTS:
            if k in values or k == "position" and not record_position:
                continue
            values[k] = out[k]
        values["subpixel"] = sub
        lens = mi.Vector2f(0.0)
        if prep.has_lens:
            lens = mi.warp.square_to_uniform_disk_concentric(aperture)
        values["lens"] = lens
        values["time"] = t_norm

    # Flatten every value into a list of Float components.
    comps: dict[str, list[Any]] = {}
    for k, v in values.items():
        if keep is not None and k not in keep:
            continue
        if isinstance(v, list):
            comps[k] = v
        elif isinstance(v, mi.Float):
            comps[k] = [v]
        else:
            comps[k] = [v[i] for i in range(len(v))]
    res: dict[str, np.ndarray] = {}
    flat = [c for cs in comps.values() for c in cs]
    dr.eval(*flat)
    if not reduce:
        return _sample_major(comps, spp=spp, h=h, W=W)

    def host(c: Any) -> np.ndarray:
        a = np.asarray(c, dtype=np.float32).reshape(-1)
        # Constant outputs (e.g. no lens) come back as one literal: broadcast them.
        return np.full(n, a[0], dtype=np.float32) if a.size == 1 and n != 1 else a

    for k, cs in comps.items():
        # Summed here rather than with dr.block_sum, which is ~6x slower than the trace on LLVM.
        arr = np.stack([host(c).reshape(h * W, spp).sum(axis=1, dtype=np.float64) for c in cs], 0)
        res[k] = arr.reshape(len(cs), h, W)
    return res


def _sample_major(comps: Mapping[str, list[Any]], *, spp: int, h: int, W: int) -> dict[str, np.ndarray]:
    """Reorder evaluated per-lane components into name -> (spp, C, h, W) float32 arrays.

    Lanes are ordered (row, column, sample) like ``mi.render``'s, because the sampler's random
    stream belongs to the lane index and the radiance must match ``mi.render`` bit for bit; the
    format wants sample-major planes, so numpy transposes each component. The destination is
    memory from Dr.Jit's allocation cache, already mapped by earlier renders: into fresh numpy
    arrays the first-touch page faults cost more than the copy itself (72 vs 13 ms at 256x256,
    8 spp on 2 cores). Tried and slower: scattering to sample-major order from inside the trace
    kernel (its time doubled: ~45 strided store streams per lane) and a Dr.Jit gather kernel.
    """
    mi = mitsuba()
    import drjit as dr

    n = spp * h * W
    # np.asarray only aliases Dr.Jit memory on the CPU (LLVM) backend.
    aliasable = dr.backend_v(mi.Float) == dr.JitBackend.LLVM
    res: dict[str, np.ndarray] = {}
    for k, cs in comps.items():
        shape = (spp, len(cs), h, W)
        if aliasable and len(cs) * n <= _MAX_JIT_WIDTH:
            buf = dr.empty(mi.Float, len(cs) * n)
            dr.make_opaque(buf)  # allocate now; numpy's view keeps the buffer alive
            arr = np.asarray(buf).reshape(shape)
        else:
            arr = np.empty(shape, dtype=np.float32)
        for i, c in enumerate(cs):
            a = np.asarray(c, dtype=np.float32).reshape(-1)
            if a.size == 1 and n != 1:
                arr[:, i] = a[0]  # constant output (e.g. no lens) comes back as one literal
            else:
                arr[:, i] = a.reshape(h, W, spp).transpose(2, 0, 1)
        res[k] = arr
    return res


#: Largest Dr.Jit array (sizes are 32-bit).
_MAX_JIT_WIDTH = 2**32 - 1


def _row_bands(width: int, height: int, spp: int, chunk_samples: int) -> list[slice]:
    rows = max(1, min(height, chunk_samples // max(1, width * spp)))
    return [slice(y, min(height, y + rows)) for y in range(0, height, rows)]


def _slice_times(seed: int, spp: int) -> np.ndarray:
    """Stratified slice times (s + u_s) / S, one per sample index."""
    rng = np.random.default_rng(derive_seed(seed, 0x51CE))
    return (np.arange(spp) + rng.random(spp)) / spp


def iter_sample_chunks(
    scene: Any,
    settings: RenderSettings,
    *,
    seed: int | None = None,
    camera_to_world: np.ndarray | None = None,
    record_position: bool = False,
    time_slices: bool | None = None,
) -> Iterator[tuple[slice, slice, dict[str, np.ndarray]]]:
    """Render per-sample data piece by piece: yields ``(samples, rows, arrays)`` with arrays
    name -> (s, C, h, W) float32. Memory stays bounded by ``settings.chunk_samples``.

    ``time_slices`` (default: on when ``settings.object_motion``) renders one sample index per
    pass with the scene posed at that index's stratified time.
    """
    seed = settings.seed if seed is None else int(seed)
    prep = _prepare(scene, settings, camera_to_world)
    channels = settings.sample_channels()
    keep = set(channels) | ({"position"} if record_position else set())
    slices = bool(settings.object_motion) if time_slices is None else bool(time_slices)
    W, H, S = settings.width, settings.height, settings.spp
    try:
        if not slices:
            bands = _row_bands(W, H, S, settings.chunk_samples)
            for i, rows in enumerate(bands):
                # One band: the seed itself, so that the result equals mi.render at that seed.
                s = seed if len(bands) == 1 else derive_seed(seed, 1, i)
                out = _trace_chunk(scene, prep, rows=rows, spp=S, seed=s, level=LEVEL_FULL, time_override=None,
                                   record_position=record_position, reduce=False, keep=keep)
                yield slice(0, S), rows, out
        else:
            times = _slice_times(seed, S)
            bands = _row_bands(W, H, 1, settings.chunk_samples)
            for si, t in enumerate(times):
                _pose_objects(prep, float(t))
                for i, rows in enumerate(bands):
                    out = _trace_chunk(scene, prep, rows=rows, spp=1, seed=derive_seed(seed, 2, si, i), level=LEVEL_FULL,
                                       time_override=float(t), record_position=record_position, reduce=False, keep=keep)
                    yield slice(si, si + 1), rows, out
    finally:
        _restore(scene, prep)


def render_samples(
    scene: Any,
    settings: RenderSettings,
    *,
    seed: int | None = None,
    time_slices: bool | None = None,
    camera_to_world: np.ndarray | None = None,
    record_position: bool = False,
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Per-sample data of the whole image: name -> (S, C, H, W) float32, and the scene features.

    ``position`` (world position of the first hit, per sample) is added when ``record_position``.
    """
    S, H, W = settings.spp, settings.height, settings.width
    arrays: dict[str, np.ndarray] = {}
    for samples, rows, chunk in iter_sample_chunks(
        scene, settings, seed=seed, camera_to_world=camera_to_world, record_position=record_position, time_slices=time_slices
    ):
        if samples == slice(0, S) and rows.start == 0 and rows.stop == H and not arrays:
            arrays = chunk  # the whole image in one piece: no copy
            continue
        for k, v in chunk.items():
            if k not in arrays:
                arrays[k] = np.zeros((S, v.shape[1], H, W), dtype=np.float32)
            arrays[k][samples, :, rows] = v
    feats = scene_features(scene)
    return arrays, feats


def render_reference(
    scene: Any,
    settings: RenderSettings,
    *,
    seed: int | None = None,
    camera_to_world: np.ndarray | None = None,
    spp: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> dict[str, np.ndarray]:
    """Reference image: name -> (C, H, W) float32 for radiance, diffuse, specular, albedo.

    ``progress`` is called with the number of camera samples traced after each chunk.

    Seeds are derived from ``seed`` under a key the per-sample input never uses, so reference and
    input noise are independent. Object motion is resolved with ``spp`` stratified time slices.
    """
    seed = settings.seed if seed is None else int(seed)
    spp = settings.ref_spp if spp is None else int(spp)
    if spp < 1:
        raise SceneError(f"render settings: reference spp={spp} must be >= 1")
    prep = _prepare(scene, settings, camera_to_world)
    W, H = settings.width, settings.height
    sums: dict[str, np.ndarray] = {}
    try:
        if settings.object_motion:
            # One slice per pass; slices stratify the shutter, so the reference converges to the
            # motion-blurred image like the input does.
            n_slices = min(spp, settings.ref_time_slices)
            per = [spp // n_slices + (1 if i < spp % n_slices else 0) for i in range(n_slices)]
            times = _slice_times(derive_seed(seed, 3), n_slices)
            passes = [(float(t), k, i) for i, (t, k) in enumerate(zip(times, per))]
        else:
            per_pass = max(1, min(spp, settings.chunk_samples // max(1, W * H)))
            passes = []
            left, i = spp, 0
            while left > 0:
                k = min(per_pass, left)
                passes.append((None, k, i))
                left -= k
                i += 1
        for t, k, i in passes:
            if t is not None:
                _pose_objects(prep, t)
            bands = _row_bands(W, H, k, settings.chunk_samples)
            for b, rows in enumerate(bands):
                out = _trace_chunk(scene, prep, rows=rows, spp=k, seed=derive_seed(seed, 4, i, b), level=LEVEL_REFERENCE,
                                   time_override=t, record_position=False, reduce=True)
                for name, v in out.items():
                    if name not in sums:
                        sums[name] = np.zeros((v.shape[0], H, W), dtype=np.float64)
                    sums[name][:, rows] += v
                if progress is not None:
                    progress(k * (rows.stop - rows.start) * W)
    finally:
        _restore(scene, prep)
    return {k: (sums[k] / spp).astype(np.float32) for k in REFERENCE_CHANNELS}


def _renderer_string() -> str:
    mi = mitsuba()
    from mcdenoise import __version__

    return f"mitsuba {mi.__version__} ({mi.variant()}) / mcdenoise {__version__}"


def render_image(
    scene: Any,
    out_dir: str | os.PathLike,
    settings: RenderSettings,
    *,
    scene_name: str = "",
    extra_meta: dict | None = None,
    camera_to_world: np.ndarray | None = None,
    record_position: bool = False,
    overwrite: bool = False,
    progress: bool = False,
    extra_noisy: dict[str, np.ndarray] | None = None,
) -> Path:
    """Render one image folder (per-sample data, noisy.exr, reference.exr, meta.json), atomically.

    The per-sample data is streamed to disk band by band, so memory stays bounded at any size.
    ``record_position`` adds a per-pixel ``position`` buffer (mean over samples) to noisy.exr;
    ``extra_noisy`` adds caller-made per-pixel layers ``(C, H, W)`` (e.g. ``motion``).
    """
    import drjit as dr

    from mcdenoise.data import format as fmt

    out = Path(out_dir)
    if out.exists() and not overwrite:
        raise SceneError(f"{out}: already exists (pass overwrite=True / --overwrite to replace it)")
    t0 = _time.perf_counter()
    channels = list(settings.sample_channels())
    feats = scene_features(scene)
    extra: dict[str, Any] = {
        "max_depth": settings.max_depth,
        "rr_depth": settings.rr_depth,
        "integrator": INTEGRATOR_NAME,
        "filter": "box",
        "time_slices": bool(settings.object_motion),
    }
    if settings.object_motion:
        extra["object_motion"] = {k: list(map(float, v)) for k, v in settings.object_motion.items()}
    if settings.camera_to_world_end is not None:
        extra["camera_to_world_end"] = np.asarray(settings.camera_to_world_end, dtype=float).tolist()
    if camera_to_world is not None:
        extra["camera_to_world"] = np.asarray(camera_to_world, dtype=float).tolist()
    extra.update(extra_meta or {})
    meta = fmt.ImageMeta(
        width=settings.width,
        height=settings.height,
        spp=settings.spp,
        channels=channels,
        scene=scene_name,
        seed=settings.seed,
        renderer=_renderer_string(),
        scene_features=feats,
        reference_spp=settings.ref_spp if settings.ref_spp > 0 else None,
        extra=extra,
    )
    writer = fmt.SampleWriter(out, meta, overwrite=overwrite)
    total = settings.width * settings.height * (settings.spp + max(0, settings.ref_spp))
    bar = tqdm(total=total, unit="sample", unit_scale=True, desc=f"render {out.name}", disable=not progress,
               leave=False, file=sys.stderr)
    try:
        pos_sum = np.zeros((3, settings.height, settings.width), dtype=np.float64) if record_position else None
        for samples, rows, chunk in iter_sample_chunks(scene, settings, camera_to_world=camera_to_world, record_position=record_position):
            if pos_sum is not None:
                pos_sum[:, rows] += chunk.pop("position").sum(axis=0, dtype=np.float64)
            for name in channels:
                writer.write(name, chunk[name], samples=samples, rows=rows)
            bar.update((samples.stop - samples.start) * (rows.stop - rows.start) * settings.width)
        # The per-sample arrays live in Dr.Jit memory (see _sample_major); once written, their
        # blocks idle in Dr.Jit's allocation cache at sizes the reference cannot reuse (+0.35 GiB
        # peak at 1024x1024, 64 spp): drop the last band's and hand them back before it starts.
        chunk = {}
        dr.flush_malloc_cache()
        t1 = _time.perf_counter()
        reference = None
        if settings.ref_spp > 0:
            reference = render_reference(scene, settings, camera_to_world=camera_to_world, progress=bar.update)
        t2 = _time.perf_counter()
        meta.extra["render_seconds"] = {"samples": round(t1 - t0, 3), "reference": round(t2 - t1, 3)}
        per_pixel = dict(extra_noisy or {})
        if pos_sum is not None:
            per_pixel["position"] = (pos_sum / settings.spp).astype(np.float32)
    except BaseException:
        writer.abort()
        raise
    finally:
        bar.close()
    return writer.finish(reference=reference, extra_noisy=per_pixel or None)
