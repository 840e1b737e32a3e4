"""Loading a Mitsuba 3 scene at a chosen film size, and what the renderer reads off it
(built-in scenes, their motion, SBMC's scene features). Every problem is one :class:`SceneError`."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Collection

import numpy as np

from mcdenoise.data.channels import SCENE_FEATURES
from mcdenoise.errors import SceneError
from mcdenoise.render._mitsuba import mitsuba
from mcdenoise.render.scenes import BUILTIN_SCENES
from mcdenoise.render.settings import MAX_SIZE

__all__ = ["list_builtin_scenes", "builtin_motion", "load_scene", "scene_features"]


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

