"""Procedural scene generator: meshes, textures, determinism, variety, rejection, exposure."""

from __future__ import annotations

import gc
from dataclasses import dataclass

import numpy as np
import pytest

from mcdenoise.errors import SceneError
from mcdenoise.render import procedural as P
from mcdenoise.render.procedural import meshes as pm
from mcdenoise.render.procedural import textures as pt

# ---------------------------------------------------------------- numpy only (no Mitsuba)


@pytest.mark.parametrize("name", sorted(pm.MESH_BUILDERS))
def test_meshes_closed_outward_and_deterministic(name: str) -> None:
    build = pm.MESH_BUILDERS[name]
    v, f, uv = build(np.random.default_rng(5))
    assert v.dtype == np.float32 and f.dtype == np.uint32 and uv.dtype == np.float32
    assert v.ndim == 2 and v.shape[1] == 3 and f.shape[1] == 3 and uv.shape == (len(v), 2)
    assert np.isfinite(v).all() and f.max() < len(v)
    # One-sided BSDFs: faces must wind outward (positive enclosed volume), and the object is
    # about unit-sized so the generator's scales mean what they say.
    assert pm.signed_volume(v, f) > 0.05
    assert 0.3 < np.abs(v).max() < 3.0
    v2, f2, uv2 = build(np.random.default_rng(5))
    np.testing.assert_array_equal(v, v2)
    np.testing.assert_array_equal(f, f2)
    v3, _, _ = build(np.random.default_rng(6))
    assert v3.shape != v.shape or not np.array_equal(v3, v)


def test_vertex_normals_of_a_sphere_are_radial() -> None:
    v, f, _ = pm.grid_surface(pm._sphere_param, 32, 16, wrap_u=True, wrap_v=False)
    f = pm._outward(v, pm._drop_degenerate(v, f))
    n = pm.vertex_normals(v, f)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, rtol=1e-6)
    # Outward and close to the radius direction (away from the poles, whose split vertices see
    # only one or two triangles each).
    body = np.abs(v[:, 1]) < 0.95
    cos = np.einsum("ij,ij->i", n[body], v[body])
    assert cos.min() > 0.98


def test_terrain_faces_up_and_is_flat_in_the_middle() -> None:
    v, f, _ = pm.terrain(np.random.default_rng(0), size=100.0, height=5.0)
    e1 = v[f[:, 1]] - v[f[:, 0]]
    e2 = v[f[:, 2]] - v[f[:, 0]]
    assert (np.cross(e1, e2)[:, 1] > 0).all()
    centre = np.linalg.norm(v[:, [0, 2]], axis=1) < 15
    assert np.abs(v[centre, 1]).max() < 0.5


@pytest.mark.parametrize("kind", pt.TEXTURE_KINDS)
def test_textures_are_reflectances_and_tile(kind: str) -> None:
    img = pt.texture_image(np.random.default_rng(1), kind, 64)
    assert img.shape == (64, 64, 3) and img.dtype == np.float32
    assert img.min() >= 0.0 and img.max() <= 1.0 and img.std() > 0.01
    # Tileable: the jump across the wrap-around seam is like the jump between neighbours.
    inner = np.abs(np.diff(img, axis=1)).mean()
    seam = np.abs(img[:, 0] - img[:, -1]).mean()
    assert seam < 4 * inner + 1e-6


def test_envmaps_are_hdr_and_finite() -> None:
    rng = np.random.default_rng(2)
    sky = pt.sky_envmap(rng, 32, 64)
    assert sky.shape == (32, 64, 3) and np.isfinite(sky).all() and sky.min() >= 0
    assert sky.max() > 50 * np.median(sky)  # a sun: real dynamic range, not an LDR picture
    studio = pt.studio_envmap(rng, 32, 64)
    assert studio.max() > 20 * np.median(studio)


def test_preview_problems() -> None:
    ok = P.PreviewStats(mean=0.3, median=0.2, black_fraction=0.01, object_fraction=0.4, finite=True)
    assert ok.problem() is None
    assert "black" in P.PreviewStats(0.0, 0.0, 1.0, 0.5, True).problem()
    assert "black" in P.PreviewStats(0.3, 0.0, 0.7, 0.5, True).problem()
    assert "objects" in P.PreviewStats(0.3, 0.2, 0.0, 0.01, True).problem()
    assert "non-finite" in P.PreviewStats(0.3, 0.2, 0.0, 0.5, False).problem()


def test_derive_seed_stable_and_distinct() -> None:
    assert P.derive_seed(0, 1) == P.derive_seed(0, 1)
    seeds = {P.derive_seed(7, i) for i in range(1000)}
    assert len(seeds) == 1000 and all(0 <= s < 2**31 for s in seeds)
    assert P.derive_seed(0, 1) != P.derive_seed(1, 0)


# ---------------------------------------------------------------- with Mitsuba


@dataclass
class Drawn:
    """What the tests need of one drawing, without its Mitsuba objects."""

    kind: str
    info: dict
    digest: str
    depth_of_field: bool
    motion_blur: bool
    sensor_type: str
    object_motion: dict
    camera_moves: bool
    object_ids: set
    emitter_shapes: set


@pytest.fixture(scope="module")
def drawn() -> dict[int, Drawn]:
    """Unchecked drawings of a few seeds (cheap: no render).

    Only summaries are kept: Dr.Jit compiles a virtual call for every live BSDF of the process,
    not just the scene's, so holding hundreds of drawn objects would slow every later render.
    """
    out = {}
    for s in range(14):
        d = P._draw(s, None, 24, 24)
        out[s] = Drawn(d.kind, d.info, P.scene_digest(d.scene), d.depth_of_field, d.motion_blur,
                       d.scene["sensor"]["type"], d.object_motion, d.camera_to_world_end is not None,
                       {k for k in d.scene if k.startswith("object_")},
                       {v["type"] for v in d.scene.values() if isinstance(v, dict) and "emitter" in v})
        del d
    gc.collect()
    return out


@pytest.mark.render
def test_same_seed_same_dict(drawn: dict[int, Drawn]) -> None:
    a = P._draw(3, None, 24, 24)
    assert P.scene_digest(a.scene) == drawn[3].digest
    assert a.info == drawn[3].info
    assert drawn[4].digest != drawn[3].digest


@pytest.mark.render
def test_variety_over_seeds(drawn: dict[int, Drawn]) -> None:
    kinds = {d.kind for d in drawn.values()}
    assert kinds == set(P.KINDS)
    mats: set[str] = set()
    tex: set[str] = set()
    shapes: set[str] = set()
    for d in drawn.values():
        mats |= set(d.info["materials"])
        tex |= set(d.info["textures"])
        shapes |= set(d.info["shapes"])
        assert P.MIN_OBJECTS <= d.info["objects"] + d.info["furniture"] <= P.MAX_OBJECTS + 30
        assert d.info["lights"] >= 1
    assert mats == set(P.MATERIALS)
    assert {"checkerboard", "noise", "stripes", "cells", "noise_stripes"} <= tex
    assert set(pm.MESH_BUILDERS) <= shapes and {"sphere", "cube"} <= shapes
    dof = [d.depth_of_field for d in drawn.values()]
    mb = [d.motion_blur for d in drawn.values()]
    assert any(dof) and not all(dof) and any(mb) and not all(mb)
    for d in drawn.values():
        assert (d.sensor_type == "thinlens") == d.depth_of_field
        assert bool(d.object_motion or d.camera_moves) == d.motion_blur
        assert set(d.object_motion) <= d.object_ids
        # Mitsuba 3.9 orders the emitters of mesh shapes differently at each load (measured),
        # which breaks reproducibility: area lights must be analytic shapes.
        assert d.emitter_shapes <= {"disk", "sphere"}


@pytest.mark.render
def test_kind_argument_and_bad_kind() -> None:
    assert P._draw(11, "indoor", 16, 16).kind == "indoor"
    assert P._draw(11, "outdoor", 16, 16).kind == "outdoor"
    with pytest.raises(SceneError, match="kind"):
        P._draw(0, "underwater", 16, 16)


def test_rejected_scene_is_redrawn_from_derived_seed(monkeypatch: pytest.MonkeyPatch) -> None:
    from mcdenoise.render.procedural import generator

    calls: list[int] = []
    rates: list[float | None] = []
    lenses: list[float | None] = []

    def fake_draw(seed: int, kind: str | None, w: int, h: int, objects: tuple[int, int],
                  world: str = "classic", small_emitters: float | None = None,
                  strong_dof: float | None = None) -> P.ProceduralScene:
        calls.append(seed)
        rates.append(small_emitters)
        lenses.append(strong_dof)
        ps = P.ProceduralScene(scene={"sky": {"type": "envmap", "scale": 1.0}}, seed=seed, drawn_seed=seed,
                               attempts=0, kind="outdoor", camera_to_world=np.eye(4), fov=40.0,
                               aperture_radius=0.0, focus_distance=1.0, depth_of_field=False,
                               motion_blur=False, shutter=(0.0, 0.0), camera_to_world_end=None,
                               object_motion={}, camera_path=(np.zeros(3), np.ones(3), np.eye(3)[1]), info={})
        return ps

    def fake_stats(ps: P.ProceduralScene, **kw: object) -> P.PreviewStats:
        if len(calls) < 3:
            return P.PreviewStats(0.0, 0.0, 1.0, 0.0, True)  # black: rejected
        return P.PreviewStats(0.4, 0.2, 0.0, 0.5, True)

    monkeypatch.setattr(generator, "_draw", fake_draw)
    monkeypatch.setattr(generator, "preview_stats", fake_stats)
    ps = P.generate(42)
    assert calls == [42, P.derive_seed(42, 1), P.derive_seed(42, 2)]
    assert ps.seed == 42 and ps.drawn_seed == calls[-1] and ps.attempts == 2
    assert len(ps.info["rejected"]) == 2
    assert rates == [None] * 3
    rates.clear()
    calls.clear()
    lenses.clear()
    P.generate(42, small_emitters=0.25, strong_dof=0.5)  # every redraw keeps the dataset's rates
    assert rates == [0.25] * 3 and lenses == [0.5] * 3
    # Exposure: emitters scaled so that the median lands on the random target in [0.05, 0.5].
    k = ps.info["emitter_scale"]
    assert ps.scene["sky"]["scale"] == pytest.approx(k)
    assert 0.05 <= 0.2 * k <= 0.5
    calls.clear()
    monkeypatch.setattr(generator, "preview_stats", lambda ps, **kw: P.PreviewStats(0.0, 0.0, 1.0, 0.0, True))
    with pytest.raises(SceneError, match="rejected"):
        P.generate(1, max_attempts=3)


def test_scale_emitters_reaches_every_emitter_kind() -> None:
    scene = {
        "type": "scene",
        "lamp": {"type": "rectangle", "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1.0, 2.0, 3.0]}}},
        "p": {"type": "point", "intensity": {"type": "rgb", "value": [4.0, 4.0, 4.0]}},
        "s": {"type": "spot", "intensity": {"type": "rgb", "value": [2.0, 2.0, 2.0]}},
        "e": {"type": "envmap", "scale": 0.5},
        "sun": {"type": "sunsky", "sun_scale": 1.0, "sky_scale": 2.0},
        "obj": {"type": "sphere", "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}}},
    }
    P._scale_emitters(scene, 3.0)
    assert scene["lamp"]["emitter"]["radiance"]["value"] == [3.0, 6.0, 9.0]
    assert scene["p"]["intensity"]["value"] == [12.0] * 3 and scene["s"]["intensity"]["value"] == [6.0] * 3
    assert scene["e"]["scale"] == 1.5 and (scene["sun"]["sun_scale"], scene["sun"]["sky_scale"]) == (3.0, 6.0)
    assert scene["obj"]["bsdf"]["reflectance"]["value"] == [0.5] * 3  # not an emitter


def _tiny(scene_extra: dict) -> P.ProceduralScene:
    from mcdenoise.render._mitsuba import mitsuba

    mi = mitsuba()
    cam = P.look_at([0, 0, -4], [0, 0, 0], [0, 1, 0])
    scene = {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40.0, "to_world": mi.ScalarTransform4f(cam.tolist()),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16, "rfilter": {"type": "box"}}},
        "object_0": {"type": "sphere", "id": "object_0", "radius": 1.0},
        **scene_extra,
    }
    return P.ProceduralScene(scene=scene, seed=0, drawn_seed=0, attempts=0, kind="outdoor", camera_to_world=cam,
                             fov=40.0, aperture_radius=0.0, focus_distance=4.0, depth_of_field=False,
                             motion_blur=False, shutter=(0.0, 0.0), camera_to_world_end=None, object_motion={},
                             camera_path=(np.zeros(3), np.ones(3), np.eye(3)[1]), info={})


@pytest.mark.render
def test_preview_check_on_real_renders() -> None:
    """The real preview check: an unlit scene is black; a lit sphere filling a fifth of the view is
    fine, and its object coverage is measured (sphere of radius 1 at distance 4, fov 40)."""
    dark = P.preview_stats(_tiny({}), size=16, spp=2)
    assert dark.problem() == "renders black"
    lit = P.preview_stats(_tiny({"sky": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}}}), size=16, spp=2)
    assert lit.problem() is None
    # Angular radius asin(1/4) against a half field of view of 20 degrees: disc of radius
    # tan(14.48)/tan(20) = 0.71 of the half width -> area fraction pi * 0.71^2 / 4 = 0.40.
    assert 0.3 < lit.object_fraction < 0.5
    assert lit.black_fraction == 0.0 and lit.median > 0.1


@pytest.mark.render
def test_generate_deterministic_and_checked() -> None:
    """Same seed, same checked scene: dict, preview pixels (the stats) and exposure agree."""
    a = P.generate(5, width=16, height=16, objects=(10, 12))
    b = P.generate(5, width=16, height=16, objects=(10, 12))
    assert a.drawn_seed == b.drawn_seed and a.attempts == b.attempts
    assert a.info["emitter_scale"] == b.info["emitter_scale"] and a.info["preview"] == b.info["preview"]
    assert P.scene_digest(a.scene) == P.scene_digest(b.scene)
    assert 10 <= a.info["objects"] + a.info["furniture"] <= 12 + 25
    assert 0.05 <= a.info["preview"]["median"] <= 0.5
    assert a.info["preview"]["object_fraction"] >= 0.08


# ---------------------------------------------------------------- views and kernel reuse


@pytest.mark.render
@pytest.mark.parametrize("kind", P.KINDS)
def test_view_cameras_stay_in_the_scene(kind: str) -> None:
    """Catches: extra views placed outside the room, inside furniture or far from the objects
    (outdoor objects only exist around the drawn view), or views that are not reproducible."""
    from mcdenoise.render.procedural.views import view_camera

    ps = P._draw(21, kind, 16, 16, (10, 12))
    origin, target, _ = ps.camera_path
    for s in range(10):
        m = view_camera(ps, np.random.default_rng(s))
        np.testing.assert_array_equal(m, view_camera(ps, np.random.default_rng(s)))
        pos = m[:3, 3]
        assert not np.allclose(pos, origin)
        if kind == "indoor":
            hx, hz, h = ps.room
            assert abs(pos[0]) < hx and abs(pos[2]) < hz and 0 < pos[1] < h
        else:
            d0 = np.linalg.norm((origin - target)[[0, 2]])
            d = np.linalg.norm((pos - target)[[0, 2]])
            assert 0.7 * d0 <= d <= 1.3 * d0 and 0.5 <= pos[1] <= 3.0
            # Looks at the drawn target (within a few degrees).
            to_t = (target - pos) / np.linalg.norm(target - pos)
            assert float(to_t @ m[:3, 2]) > 0.95


@pytest.mark.render
@pytest.mark.parametrize("seed,kind,sky", [
    (5, "indoor", None),
    # Fixed (issue 18): this one compiled once more after the exposure fix, because its thin-lens
    # camera's aperture and focus distance were literals until the first update after a render.
    (3, "outdoor", "envmap"),
])
def test_new_view_and_exposure_reuse_the_compiled_kernel(seed: int, kind: str, sky: str | None) -> None:
    """Catches: the camera pose or an emitter rescale (area/point/spot lights indoors, the
    envmap's scale outdoors) reaching the kernel as a literal, so that every view (and the
    exposure fix after the preview) compiles the whole scene again: the cost the issue measured
    (seconds per image); and the sample count becoming a literal (generator 3 checks extra views
    at fewer spp with the input's kernel). Sunsky scenes are the documented exception (Mitsuba bakes its scale)."""
    from dataclasses import replace

    import drjit as dr

    from mcdenoise.render.api import RenderSettings, render_samples
    from mcdenoise.render.procedural.views import set_camera, view_camera

    settings = RenderSettings(spp=2, ref_spp=0, width=16, height=16, seed=3)
    was = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()  # drop older entries
        ps = P.generate(seed, kind=kind, width=16, height=16, objects=(10, 12), settings=settings, keep_loaded=True)
        assert (ps.scene.get("sky") or {}).get("type") == sky and not ps.object_motion
        assert any((k.get("operation_count") or 0) > 1000 for k in dr.kernel_history())  # the preview compiled
        render_samples(ps.loaded, settings)  # after the emitter rescale
        set_camera(ps.loaded, view_camera(ps, np.random.default_rng(0)))
        render_samples(ps.loaded, settings)  # another view
        render_samples(ps.loaded, replace(settings, spp=1))  # generator 3's cheap view check
        big = [k for k in dr.kernel_history() if (k.get("operation_count") or 0) > 1000]
        # In-memory reuse only: ``cache_hit`` is also true for a kernel loaded from the disk cache,
        # which hides a real second trace and compile-or-load on a warm machine (issue 18).
        reused = [bool(k["cache_hit"]) and not k.get("cache_disk") for k in big]
        assert len(big) >= 2 and all(reused), [(k["operation_count"], k["cache_hit"], k.get("cache_disk")) for k in big]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was)


@pytest.mark.render
def test_emitters_rescaled_in_place_match_a_fresh_load() -> None:
    """Catches: the in-place exposure fix missing an emitter kind or scaling it differently from
    the rescaled dict that meta.json describes."""
    from mcdenoise.render.api import RenderSettings, render_samples

    settings = RenderSettings(spp=2, ref_spp=0, width=12, height=12, seed=1, channels=("radiance",))
    for seed, kind, sky in ((5, "indoor", None), (3, "outdoor", "envmap")):
        ps = P.generate(seed, kind=kind, width=12, height=12, objects=(10, 12), settings=settings, keep_loaded=True)
        assert (ps.scene.get("sky") or {}).get("type") == sky
        assert ps.info["emitter_scale"] != 1.0
        a = render_samples(ps.loaded, settings)[0]["radiance"]
        ps.loaded = None
        gc.collect()
        fresh = P.load_procedural(ps, 12, 12)
        b = render_samples(fresh, settings)[0]["radiance"]
        del fresh
        gc.collect()
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)


def test_reference_time_slices_follow_on_screen_motion() -> None:
    """Catches: a reference slice count that ignores how far objects move on screen (visible
    ghost copies of fast objects, or 256 costly slices for motion under a pixel), or that
    forgets depth (near objects move more pixels) or objects behind the camera."""
    from mcdenoise.render.procedural.views import motion_pixels, reference_time_slices

    cam = P.look_at([0, 0, 0], [0, 0, 10], [0, 1, 0])  # +Z forward
    ps = P.ProceduralScene(scene={}, seed=0, drawn_seed=0, attempts=0, kind="outdoor", camera_to_world=cam,
                           fov=90.0, aperture_radius=0.0, focus_distance=10.0, depth_of_field=False, motion_blur=True,
                           shutter=(0.0, 1.0), camera_to_world_end=None, object_motion={"object_0": [1.0, 0.0, 0.0]},
                           camera_path=(np.zeros(3), np.array([0, 0, 10.0]), np.eye(3)[1]), info={},
                           extents={"object_0": (np.array([0.0, 0.0, 10.0]), 0.5)})
    # fov 90 on 64 pixels: 32 pixels per unit at depth 1; nearest point at depth 9.5.
    assert motion_pixels(ps, cam, 64) == pytest.approx(32 / 9.5)
    assert reference_time_slices(ps, cam, 64) == 8  # clipped up: 3.4 px needs 7
    ps.object_motion = {"object_0": [5.0, 0.0, 0.0]}
    assert reference_time_slices(ps, cam, 64) == int(np.ceil(2 * 5 * 32 / 9.5))  # ghosts <= 0.5 px apart
    ps.extents = {"object_0": (np.array([0.0, 0.0, 2.0]), 0.5)}  # nearer: more pixels
    assert reference_time_slices(ps, cam, 64) == 214
    ps.extents = {"object_0": (np.array([0.0, 0.0, -3.0]), 0.5)}  # behind the camera
    assert reference_time_slices(ps, cam, 64) == 256
    ps.object_motion = {}
    assert motion_pixels(ps, cam, 64) == 0.0
