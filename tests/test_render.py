"""Renderer tests on tiny renders (<= 32x32, 4 spp), one loaded scene per module fixture."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.render

SCENES = Path(__file__).parent / "fixtures" / "scenes"
FIXTURE_XML = SCENES / "thinlens_textured.xml"
W, H, S = 32, 24, 4


@pytest.fixture(scope="module")
def cornell(mi):
    from mcdenoise.render import load_scene

    return load_scene("cornell-box", width=W, height=H)


@pytest.fixture(scope="module")
def settings():
    from mcdenoise.render import RenderSettings

    return RenderSettings(spp=S, ref_spp=16, width=W, height=H, seed=3)


@pytest.fixture(scope="module")
def samples(cornell, settings):
    from mcdenoise.render import render_samples

    return render_samples(cornell, settings, record_position=True)


@pytest.fixture(scope="module")
def xml_scene(mi):
    from mcdenoise.render import load_scene

    return load_scene(FIXTURE_XML, width=W, height=H)


def _mi_render(mi, scene, spp: int, seed: int, max_depth: int = 6) -> np.ndarray:
    from mcdenoise.render.emitter_order import emitter_order

    integ = mi.load_dict({"type": "mcdenoise_path", "max_depth": max_depth})
    integ.emitter_order = emitter_order(mi, scene)  # as the renderer sets it (None unless mesh emitters)
    return np.array(mi.render(scene, integrator=integ, spp=spp, seed=seed)).transpose(2, 0, 1)


# ----------------------------------------------------------------------------- exactness


def test_pixel_means_equal_mi_render(mi, cornell, samples, settings):
    arrays, _ = samples
    ours = arrays["radiance"].mean(axis=0)
    ref = _mi_render(mi, cornell, settings.spp, settings.seed)
    assert ours.shape == ref.shape == (3, H, W)
    assert ref.mean() > 0.01  # the scene is lit
    # Same paths, same random numbers: equal up to the order of the float32 pixel sums.
    np.testing.assert_allclose(ours, ref, rtol=2e-6, atol=1e-7)
    assert np.mean(ours == ref) > 0.95


def test_pixel_means_equal_mi_render_thinlens_textures(mi, xml_scene):
    from mcdenoise.render import RenderSettings, render_samples

    st = RenderSettings(spp=S, ref_spp=0, width=W, height=H, seed=11)
    arrays, feats = render_samples(xml_scene, st)
    ours = arrays["radiance"].mean(axis=0)
    ref = _mi_render(mi, xml_scene, S, 11)
    np.testing.assert_allclose(ours, ref, rtol=2e-6, atol=1e-7)
    assert feats["aperture_radius"] == pytest.approx(0.15)
    assert feats["focus_distance"] == pytest.approx(5.0)
    assert feats["fov"] == pytest.approx(40.0)
    lens = arrays["lens"]
    r = np.sqrt((lens**2).sum(axis=1))
    assert r.max() <= 1.0 + 1e-6 and r.max() > 0.9  # fills the unit disk
    assert abs(float(lens.mean())) < 0.05
    # The lens record is the aperture sample mi.render used: a different lens sample would
    # give a different image, so exactness above also pins the lens records.


def _film_rewritten(src: Path, dst: Path, width: int, height: int, extra: str = "") -> Path:
    """``src`` with its film's width/height literals replaced by text substitution (independent of
    load_scene's own rewrite) and ``extra`` added inside the film; written to ``dst``."""
    import re

    text = src.read_text()
    text = re.sub(r'(<integer name="width" value=")[^"]*', rf"\g<1>{width}", text)
    text = re.sub(r'(<integer name="height" value=")[^"]*', rf"\g<1>{height}", text)
    text = text.replace("<rfilter", extra + "<rfilter", 1)
    dst.write_text(text)
    return dst


def _relmse(x: np.ndarray, ref: np.ndarray) -> float:
    """Per-pixel relative MSE, averaged: mean((x - ref)^2 / (ref^2 + 0.01))."""
    return float(np.mean((x - ref) ** 2 / (ref**2 + 1e-2)))


@pytest.mark.parametrize(
    "name, defines, size",
    [
        # fov given for the smaller axis: the x field of view depends on the aspect ratio.
        ("thinlens_textured.xml", {"fov_axis": "smaller"}, (32, 24)),
        # focal length on a 96x64 film rendered square: the field of view depends on the aspect.
        ("perspective_focal.xml", {}, (32, 32)),
        # 48x72 film rendered at another aspect: the view extent follows the film.
        ("orthographic_portrait.xml", {}, (32, 24)),
    ],
)
def test_size_gives_the_camera_mitsuba_builds_for_it(mi, tmp_path, name, defines, size):
    """Bug (issue 8, item 11): load_scene(width=, height=) resized the film of the loaded scene,
    which keeps the projection built for the file's size: per pixel relMSE 0.15 (thinlens,
    fov_axis=smaller) and 0.14 (focal_length) against Mitsuba's own render of the file at that size.
    Our per-pixel means must equal mi.render of the file loaded at that size, pixel by pixel."""
    from mcdenoise.render import RenderSettings, load_scene, render_samples

    w, h = size
    spp, seed = 64, 5
    scene = load_scene(SCENES / name, defines=defines, width=w, height=h)
    arrays, _ = render_samples(scene, RenderSettings(spp=spp, ref_spp=0, width=w, height=h, seed=seed))
    ours = arrays["radiance"].mean(axis=0)
    theirs_scene = mi.load_file(str(_film_rewritten(SCENES / name, tmp_path / name, w, h)), **defines)
    theirs = _mi_render(mi, theirs_scene, spp, seed)
    assert ours.shape == theirs.shape == (3, h, w) and theirs.mean() > 0.01
    # Same camera, same random numbers: equal up to float32 summation order (a wrong camera
    # gives relMSE > 0.1 here; the noise between two seeds is ~0.015).
    assert _relmse(ours, theirs) < 1e-8
    np.testing.assert_allclose(ours, theirs, rtol=2e-6, atol=1e-7)
    if name.startswith("thinlens"):
        lens = arrays["lens"]
        assert np.sqrt((lens**2).sum(axis=1)).max() > 0.9  # the lens is sampled: depth of field kept


def test_crop_window_renders_like_mitsuba_and_refuses_a_new_size(mi, tmp_path):
    """A film with a crop window renders that window (as mi.render does) at the file's size; a new
    size is refused with a message that names the crop window, rather than silently moving it."""
    from mcdenoise.errors import SceneError
    from mcdenoise.render import RenderSettings, load_scene, render_samples

    crop = ('<integer name="crop_offset_x" value="40"/><integer name="crop_offset_y" value="20"/>'
            '<integer name="crop_width" value="24"/><integer name="crop_height" value="16"/>')
    path = _film_rewritten(SCENES / "perspective_focal.xml", tmp_path / "crop.xml", 96, 64, crop)
    scene = load_scene(path)
    film = scene.sensors()[0].film().crop_size()
    assert (int(film[0]), int(film[1])) == (24, 16)
    arrays, _ = render_samples(scene, RenderSettings(spp=16, ref_spp=0, width=24, height=16, seed=2))
    theirs = _mi_render(mi, mi.load_file(str(path)), 16, 2)
    assert theirs.shape == (3, 16, 24) and theirs.mean() > 0.01
    np.testing.assert_allclose(arrays["radiance"].mean(axis=0), theirs, rtol=2e-6, atol=1e-7)
    with pytest.raises(SceneError, match="crop window"):
        load_scene(path, width=32, height=32)
    # Settings of another size than the loaded film: refused, not resized behind the caller's back.
    with pytest.raises(SceneError, match="load the scene at the size"):
        render_samples(scene, RenderSettings(spp=1, ref_spp=0, width=32, height=32))


def test_resized_xml_finds_files_next_to_it(mi, tmp_path, monkeypatch):
    """The resized scene is loaded from a string; relative paths (meshes, includes) must still
    resolve against the file's folder, not the working directory, and the resolver is restored."""
    from mcdenoise.render import load_scene

    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "tri.obj").write_text("v -1 -1 0\nv 1 -1 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "scene" / "light.xml").write_text(
        '<scene version="3.0.0"><emitter type="constant"><rgb name="radiance" value="1"/></emitter></scene>')
    (tmp_path / "scene" / "s.xml").write_text("""<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="64"/><integer name="height" value="64"/></film>
  </sensor>
  <shape type="obj"><string name="filename" value="tri.obj"/></shape>
  <include filename="light.xml"/>
</scene>""")
    monkeypatch.chdir(tmp_path)
    before = len(mi.file_resolver())
    scene = load_scene(Path("scene") / "s.xml", width=12, height=10)
    assert len(scene.shapes()) == 1 and len(scene.emitters()) == 1
    assert len(mi.file_resolver()) == before
    film = scene.sensors()[0].film().crop_size()
    assert (int(film[0]), int(film[1])) == (12, 10)


def test_define_that_only_sized_the_film_yields_to_the_size(mi):
    """``-D res=128 --size 20x10`` on a film sized by $res: the explicit size wins (Mitsuba would
    refuse the then unused $res); a -D the scene never uses is still refused, by name."""
    from mcdenoise.errors import SceneError
    from mcdenoise.render import load_scene

    scene = load_scene(FIXTURE_XML, defines={"res": "128", "radius": "0.3"}, width=20, height=10)
    film = scene.sensors()[0].film().crop_size()
    assert (int(film[0]), int(film[1])) == (20, 10)
    film = load_scene(FIXTURE_XML, defines={"res": "40"}).sensors()[0].film().crop_size()
    assert (int(film[0]), int(film[1])) == (40, 40)
    with pytest.raises(SceneError, match="nosuch"):
        load_scene(FIXTURE_XML, defines={"nosuch": "1"}, width=20, height=10)


def test_dict_scene_size_is_set_before_loading(mi):
    """Scene dicts get the film size before load_dict too: the x field of view equals that of the
    dict loaded by Mitsuba with that film (fov_axis=smaller makes it depend on the aspect)."""
    from mcdenoise.errors import SceneError
    from mcdenoise.render import load_scene

    def scene_dict(w: int, h: int, **film: int) -> dict:
        return {
            "type": "scene",
            "cam": {"type": "perspective", "fov": 40.0, "fov_axis": "smaller",
                    "film": {"type": "hdrfilm", "width": w, "height": h, **film}},
            "ball": {"type": "sphere"},
        }

    ours = load_scene(scene_dict(30, 40), width=40, height=30)
    theirs = mi.load_dict(scene_dict(40, 30))
    fov = [float(np.asarray(mi.traverse(s.sensors()[0])["x_fov"]).reshape(-1)[0]) for s in (ours, theirs)]
    assert fov[0] == pytest.approx(fov[1], rel=1e-6) and abs(fov[0] - 40.0) > 1.0
    with pytest.raises(SceneError, match="crop window"):
        load_scene(scene_dict(96, 64, crop_width=10, crop_height=10), width=30, height=40)


def test_diffuse_plus_specular_is_total(samples):
    arrays, _ = samples
    tot = arrays["diffuse"] + arrays["specular"]
    np.testing.assert_allclose(tot, arrays["radiance"], rtol=1e-5, atol=1e-6)
    assert arrays["diffuse"].min() >= 0 and arrays["specular"].min() >= -1e-6
    # Both parts carry energy in a scene with diffuse walls and a glossy/glass sphere.
    assert arrays["diffuse"].mean() > 0.01 and arrays["specular"].mean() > 0.005


def test_feature_ranges(samples):
    arrays, _ = samples
    hit = arrays["depth"][:, 0] > 0
    assert 0.5 < hit.mean() <= 1.0
    n = np.sqrt((arrays["normal"] ** 2).sum(axis=1))
    np.testing.assert_allclose(n[hit], 1.0, atol=1e-4)
    assert np.all(n[~hit] == 0)
    for name in ("albedo", "albedo_diffuse", "roughness", "visibility", "lobes", "subpixel"):
        v = arrays[name]
        assert v.min() >= 0.0 and v.max() <= 1.0, name
    assert arrays["subpixel"].max() < 1.0 and 0.4 < arrays["subpixel"].mean() < 0.6
    for name in ("visibility", "lobes"):
        assert set(np.unique(arrays[name])) <= {0.0, 1.0}, name
    pl = arrays["path_length"]
    assert np.all(pl == np.round(pl)) and pl.max() <= 6
    # A path that hit something has at least one lobe at vertex 1 unless it hit only the light.
    lobes1 = arrays["lobes"][:, 0:5].sum(axis=1)
    assert np.all(lobes1[~hit] == 0)
    assert (lobes1[hit] > 0).mean() > 0.9
    # Roughness: diffuse walls are 1, the rough gold sphere 0.15, glass 0.
    vals = np.unique(arrays["roughness"][:, 0][hit]).astype(np.float64)
    for want in (1.0, 0.15, 0.0):
        assert np.abs(vals - want).min() < 1e-6, (want, vals)
    # depth_diffuse >= depth (the first diffuse hit is at or after the first hit).
    dd, d = arrays["depth_diffuse"], arrays["depth"]
    found = dd > 0
    assert np.all(dd[found] >= d[found] - 1e-4)
    # World position: on the Cornell box's surfaces (inside [-1, 1]^3 up to epsilon).
    pos = arrays["position"][:, :, :, :][np.broadcast_to(hit[:, None], arrays["position"].shape)]
    assert np.abs(pos).max() <= 1.0 + 1e-3
    assert set(arrays) >= {"radiance", "lens", "time"}
    assert np.all(arrays["time"] == 0) and np.all(arrays["lens"] == 0)  # static pinhole camera


def test_determinism_per_seed(cornell, settings, samples):
    from dataclasses import replace

    from mcdenoise.render import render_samples

    arrays, _ = samples
    again, _ = render_samples(cornell, settings, record_position=True)
    for k in arrays:
        np.testing.assert_array_equal(again[k], arrays[k], err_msg=k)
    other, _ = render_samples(cornell, replace(settings, seed=settings.seed + 1))
    assert not np.array_equal(other["radiance"], arrays["radiance"])
    assert not np.array_equal(other["subpixel"], arrays["subpixel"])


def test_new_seed_does_not_recompile(mi, cornell, settings, samples):
    import drjit as dr

    from mcdenoise.render import render_samples

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()  # clears
        render_samples(cornell, settings, seed=987654)
        hist = [k for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert hist, "no JIT kernel launched"
    # In memory, not from the disk cache (which a warm machine would also report as a hit).
    assert all(k.get("cache_hit") and not k.get("cache_disk") for k in hist), \
        [(k.get("cache_hit"), k.get("cache_disk")) for k in hist]


def test_chunked_render_is_consistent(cornell, settings, samples):
    """Row bands (small chunk_samples) give the same statistics and valid records."""
    from dataclasses import replace

    from mcdenoise.render import render_samples

    arrays, _ = samples
    chunked, _ = render_samples(cornell, replace(settings, chunk_samples=W * S * 5))
    assert chunked["radiance"].shape == arrays["radiance"].shape
    # Different seeds per band: not identical, but the geometry records at the same sub-pixel
    # positions are deterministic functions of the ray, so the depth maps agree on average.
    assert not np.array_equal(chunked["radiance"], arrays["radiance"])
    assert abs(chunked["depth"].mean() - arrays["depth"].mean()) < 0.05 * arrays["depth"].mean()


# ----------------------------------------------------------------------------- references


def test_reference_channels_and_independence(cornell, settings, samples):
    from mcdenoise.render import render_reference

    arrays, _ = samples
    ref = render_reference(cornell, settings, spp=64)
    assert set(ref) == {"radiance", "diffuse", "specular", "albedo"}
    for v in ref.values():
        assert v.shape[1:] == (H, W) and v.dtype == np.float32
    np.testing.assert_allclose(ref["diffuse"] + ref["specular"], ref["radiance"], rtol=1e-4, atol=1e-5)
    noisy = arrays["radiance"].mean(axis=0)
    assert abs(ref["radiance"].mean() / noisy.mean() - 1) < 0.25  # 4 spp input: caustic fireflies
    # Independent seeds: the reference is not the input re-averaged.
    ref4 = render_reference(cornell, settings, spp=S)
    assert not np.allclose(ref4["radiance"], noisy)
    # Albedo is nearly noise-free (it varies only across edges inside a pixel).
    assert np.abs(ref["albedo"] - arrays["albedo"].mean(axis=0)).mean() < 0.02


@pytest.mark.slow
def test_unbiased_against_mitsuba_path(mi, cornell, settings):
    """Image mean within 0.5% of Mitsuba's own `path` integrator at high spp."""
    from dataclasses import replace

    from mcdenoise.render import render_reference

    ref = render_reference(cornell, replace(settings, ref_spp=4096))
    path = mi.load_dict({"type": "path", "max_depth": settings.max_depth})
    img = np.mean([np.array(mi.render(cornell, integrator=path, spp=1024, seed=100 + k)) for k in range(4)], axis=0)
    assert abs(ref["radiance"].mean() / img.mean() - 1) < 0.005


# ----------------------------------------------------------------------------- motion


def test_object_motion_time_slices_converge(mi):
    from mcdenoise.render import RenderSettings, builtin_motion, load_scene, render_reference, render_samples

    scene = load_scene("cornell-motion", width=16, height=16)
    motion = builtin_motion("cornell-motion")
    st = RenderSettings(spp=16, ref_spp=0, width=16, height=16, seed=5, **motion)
    blurred, feats = render_samples(scene, st)
    assert feats["shutter_close"] - feats["shutter_open"] == pytest.approx(1.0)
    t = blurred["time"][:, 0]
    # One stratified slice per sample index: every pixel of sample s shares time in [s/S, (s+1)/S).
    for s in range(st.spp):
        assert np.all(t[s] == t[s, 0, 0]) and s / st.spp <= t[s, 0, 0] < (s + 1) / st.spp
    # First-hit albedo is nearly noise-free, so it shows the blur without radiance noise.
    target = render_reference(scene, st, spp=128)["albedo"]  # 128 stratified slices
    static, _ = render_samples(scene, RenderSettings(spp=16, ref_spp=0, width=16, height=16, seed=5))
    err_blur = np.mean((blurred["albedo"].mean(0) - target) ** 2)
    err_static = np.mean((static["albedo"].mean(0) - target) ** 2)
    assert err_blur < 0.5 * err_static, (err_blur, err_static)
    # More slices converge further.
    st64 = RenderSettings(spp=64, ref_spp=0, width=16, height=16, seed=6, **motion)
    blurred64, _ = render_samples(scene, st64)
    err64 = np.mean((blurred64["albedo"].mean(0) - target) ** 2)
    assert err64 < err_blur, (err64, err_blur)
    # The scene is left as loaded.
    after, _ = render_samples(scene, RenderSettings(spp=16, ref_spp=0, width=16, height=16, seed=5))
    np.testing.assert_array_equal(after["radiance"], static["radiance"])


def _octahedron_scene(mi) -> dict:
    """A moving mesh (no ``to_world`` parameter, so it moves by its vertices) whose normals are
    not the face-averaged ones Mitsuba would compute."""
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float32)
    f = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]], np.uint32)
    mesh = mi.Mesh("octa", len(v), len(f), has_vertex_normals=True)
    p = mi.traverse(mesh)
    p["vertex_positions"] = mi.Float(v.ravel())
    p["faces"] = mi.UInt32(f.ravel())
    # Tilted away from the face averages (which are radial on this symmetric solid).
    n = v + np.float32([0.3, 0.5, 0.0])
    p["vertex_normals"] = mi.Float((n / np.linalg.norm(n, axis=1, keepdims=True)).astype(np.float32).ravel())
    p.update()
    return {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40, "shutter_open": 0.0, "shutter_close": 1.0,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16}},
        "octa": mesh,
        "light": {"type": "point", "position": [2.0, 3.0, 4.0], "intensity": {"type": "rgb", "value": 30.0}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.2}},
    }


def test_moving_mesh_keeps_its_normals_and_renders_reproducibly(mi):
    """Catches the time slices recomputing a moved mesh's normals: a mesh moved by its vertex
    positions had its vertex normals replaced by Mitsuba's face averages (a translated object then
    shaded differently from the loaded one, and views after the first kept the wrong normals),
    and that recomputation sums with parallel atomics, so a reference with object motion changed
    from run to run in the last bits (measured ~1e-6 on a procedural scene)."""
    from mcdenoise.render import RenderSettings, load_scene, render_reference, render_samples

    scene = load_scene(_octahedron_scene(mi))
    params = mi.traverse(scene)
    loaded = np.array(params["octa.vertex_normals"])
    st = RenderSettings(spp=4, ref_spp=16, ref_time_slices=16, width=16, height=16, seed=4,
                        object_motion={"octa": (0.6, 0.2, 0.0)})
    static_st = RenderSettings(spp=4, ref_spp=0, width=16, height=16, seed=4)
    before, _ = render_samples(scene, static_st)
    ref1 = render_reference(scene, st)
    np.testing.assert_array_equal(np.array(mi.traverse(scene)["octa.vertex_normals"]), loaded)
    render_samples(scene, st)
    ref2 = render_reference(scene, st)
    for k in ref1:
        np.testing.assert_array_equal(ref1[k], ref2[k])
    # The scene is left exactly as loaded (normals included), so a later static render is unchanged.
    after, _ = render_samples(scene, static_st)
    np.testing.assert_array_equal(after["radiance"], before["radiance"])
    np.testing.assert_array_equal(after["normal"], before["normal"])


def test_camera_motion_exact_per_ray(mi):
    """Every sample sees the world from the camera at its own time: |position - origin(t)| = depth."""
    from mcdenoise.render import RenderSettings, builtin_motion, load_scene, render_samples

    scene = load_scene("cornell-camera-motion", width=16, height=16)
    motion = builtin_motion("cornell-camera-motion")
    st = RenderSettings(spp=4, ref_spp=0, width=16, height=16, seed=2, **motion)
    arrays, _ = render_samples(scene, st, record_position=True)
    t = arrays["time"][:, 0]
    assert 0 <= t.min() and t.max() < 1 and t.std() > 0.2
    start = np.array([[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 3.9], [0, 0, 0, 1]], float)
    o0, o1 = start[:3, 3], np.asarray(motion["camera_to_world_end"])[:3, 3]
    origin = o0[:, None, None, None] * (1 - t) + o1[:, None, None, None] * t  # (3, S, H, W)
    pos = arrays["position"].transpose(1, 0, 2, 3)
    depth = arrays["depth"][:, 0]
    hit = depth > 0
    dist = np.sqrt(((pos - origin) ** 2).sum(axis=0))
    # Mitsuba starts camera rays on the near-clip plane (near_clip = 1e-3 along the axis).
    gap = dist[hit] - depth[hit]
    assert gap.min() > 0.9e-3 and gap.max() < 1.3e-3, (gap.min(), gap.max())
    # Not a static camera: distances from the start origin disagree for late samples.
    dist0 = np.sqrt(((pos - o0[:, None, None, None]) ** 2).sum(axis=0))
    late = hit & (t > 0.5)
    assert np.abs(dist0[late] - depth[late]).mean() > 0.01  # 10x the near-clip gap


def test_new_camera_motion_reuses_the_compiled_kernel(mi):
    """Catches: the camera's start/end poses reaching the kernel as literals, so that every view of
    a procedural scene with camera motion compiled its own kernels (2 s per view at 64x64 on the
    project's machine, the larger part of such a view's cost)."""
    import drjit as dr

    from mcdenoise.render import RenderSettings, builtin_motion, load_scene, render_samples

    scene = load_scene("cornell-camera-motion", width=16, height=16)
    end = np.asarray(builtin_motion("cornell-camera-motion")["camera_to_world_end"], float)
    was = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()  # drop older entries
        st = RenderSettings(spp=2, ref_spp=0, width=16, height=16, seed=2, camera_to_world_end=end)
        first, _ = render_samples(scene, st)
        moved = end.copy()
        moved[:3, 3] += [0.1, -0.05, 0.2]
        second, _ = render_samples(scene, RenderSettings(spp=2, ref_spp=0, width=16, height=16, seed=2,
                                                         camera_to_world_end=moved))
        big = [k for k in dr.kernel_history() if (k.get("operation_count") or 0) > 1000]
        assert len(big) >= 2, [k.get("operation_count") for k in dr.kernel_history()]
        # The second render is the same kernel from memory (not the disk cache: see test_procedural).
        assert bool(big[-1]["cache_hit"]) and not big[-1].get("cache_disk"), big[-1]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was)
    assert not np.array_equal(first["radiance"], second["radiance"])  # the new end pose took effect


def test_camera_override(mi, cornell, settings, samples):
    from dataclasses import replace

    from mcdenoise.render import render_samples

    arrays, _ = samples
    moved = np.array([[-1, 0, 0, 0.2], [0, 1, 0, 0], [0, 0, -1, 3.9], [0, 0, 0, 1]], float)
    other, _ = render_samples(cornell, replace(settings, ref_spp=0), camera_to_world=moved, record_position=True)
    assert not np.allclose(other["depth"], arrays["depth"])
    # The override is temporary: the scene renders as before afterwards.
    again, _ = render_samples(cornell, settings, record_position=True)
    np.testing.assert_array_equal(again["radiance"], arrays["radiance"])


# ----------------------------------------------------------------------------- image folders, CLI, errors


def test_render_image_folder(tmp_path, cornell, settings):
    from mcdenoise.data.format import read_image
    from mcdenoise.errors import SceneError
    from mcdenoise.render import render_image

    motion = np.full((2, H, W), 0.25, np.float32)
    out = render_image(cornell, tmp_path / "img", settings, scene_name="cornell-box", record_position=True,
                       extra_noisy={"motion": motion})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["img"]  # nothing left aside
    img = read_image(out)
    assert img.meta.spp == S and img.meta.reference_spp == 16 and img.meta.scene == "cornell-box"
    assert img.meta.extra["max_depth"] == settings.max_depth
    assert set(img.meta.scene_features) == {"fov", "aperture_radius", "focus_distance", "shutter_open", "shutter_close"}
    noisy = img.read_noisy()
    assert "radiance_variance" in noisy and "position" in noisy
    # Every per-pixel input a pixel model reads is written by default, e.g. KPCN's first-diffuse
    # albedo/normal/depth (issue 8 item 5) and their variances.
    from mcdenoise.models.registry import build_model

    for name in ("kpcn", "dpcn", "kpcn_single"):
        missing = [c for c in build_model(name, "small").required_channels() if c not in noisy]
        assert not missing, (name, missing)
    np.testing.assert_array_equal(noisy["motion"], motion)
    # Per-pixel position is the mean first-hit position: inside the box.
    assert np.abs(noisy["position"]).max() <= 1.0 + 1e-3 and np.abs(noisy["position"]).mean() > 0.1
    ref = img.read_reference()
    assert ref is not None and ref["radiance"].shape == (3, H, W)
    smp = img.samples.read(["radiance", "lobes"])
    assert smp["radiance"].shape == (S, 3, H, W) and smp["lobes"].shape == (S, 15, H, W)
    np.testing.assert_allclose(noisy["radiance"], smp["radiance"].mean(0), rtol=1e-5, atol=1e-6)
    with pytest.raises(SceneError, match="already exists"):
        render_image(cornell, out, settings)


def _bad_scene(tmp_path: Path, body: str) -> Path:
    p = tmp_path / "bad.xml"
    p.write_text(f'<scene version="3.0.0">{body}</scene>')
    return p


def test_errors_are_one_line(tmp_path, mi):
    from mcdenoise.errors import SceneError
    from mcdenoise.render import RenderSettings, load_scene

    cases = [
        (tmp_path / "missing.xml", "no such scene file"),
        (_bad_scene(tmp_path, '<shape type="nosuchshape"/>'), "nosuchshape"),
    ]
    for path, needle in cases:
        with pytest.raises(SceneError) as ei:
            load_scene(path)
        msg = str(ei.value)
        assert "\n" not in msg and str(path) in msg and needle in msg, msg
    nosensor = tmp_path / "nosensor.xml"
    nosensor.write_text('<scene version="3.0.0"><shape type="sphere"/></scene>')
    # Mitsuba adds a default sensor to scenes without one; either way the error/scene is usable.
    try:
        load_scene(nosensor)
    except SceneError as e:
        assert "sensor" in str(e)
    with pytest.raises(SceneError, match="out of range"):
        load_scene("cornell-box", width=0, height=10)
    with pytest.raises(SceneError, match="spp"):
        RenderSettings(spp=0).check()
    with pytest.raises(SceneError, match="width"):
        RenderSettings(width=100000).check()


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mcdenoise.cli.main", "render", *args],
                          capture_output=True, text=True, timeout=600)


def test_cli_list_and_errors(tmp_path):
    r = _cli("--list")
    assert r.returncode == 0
    names = [ln.split()[0] for ln in r.stdout.splitlines()]
    assert {"cornell-box", "cornell-dof", "cornell-motion"} <= set(names)
    r = _cli(str(tmp_path / "nope.xml"), "--out", str(tmp_path / "o"))
    assert r.returncode == 1 and r.stderr.count("\n") == 1 and "nope.xml" in r.stderr
    r = _cli("cornell-box", "--size", "0x5", "--out", str(tmp_path / "o"))
    assert r.returncode == 1 and "--size" in r.stderr


def test_cli_renders_xml_with_defines(tmp_path):
    out = tmp_path / "xml"
    r = _cli(str(FIXTURE_XML), "--spp", "2", "--ref-spp", "4", "--size", "16x12", "--seed", "4",
             "--max-depth", "4", "-D", "radius=0.3", "--out", str(out))
    assert r.returncode == 0, r.stderr
    meta = json.loads((out / "meta.json").read_text())
    assert meta["width"] == 16 and meta["height"] == 12 and meta["spp"] == 2 and meta["seed"] == 4
    assert meta["extra"]["max_depth"] == 4 and meta["extra"]["defines"] == {"radius": "0.3"}
    assert meta["scene_features"]["aperture_radius"] == pytest.approx(0.15)
    assert (out / "reference.exr").exists() and (out / "noisy.exr").exists()


def test_mitsuba_06_file_is_upgraded(tmp_path, mi):
    """A 0.6-format file (camelCase parameters) loads through Mitsuba 3's upgrade and renders."""
    from mcdenoise.render import RenderSettings, load_scene, render_samples

    p = tmp_path / "old.xml"
    p.write_text("""<scene version="0.6.0">
  <sensor type="thinlens">
    <float name="fov" value="45"/>
    <float name="apertureRadius" value="0.05"/>
    <float name="focusDistance" value="4"/>
    <transform name="toWorld"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
  </sensor>
  <shape type="sphere"><bsdf type="dielectric"><float name="intIOR" value="1.33"/></bsdf></shape>
  <emitter type="constant"><spectrum name="radiance" value="1"/></emitter>
</scene>""")
    scene = load_scene(p)
    arrays, feats = render_samples(scene, RenderSettings(spp=2, ref_spp=0, width=8, height=8))
    assert feats["aperture_radius"] == pytest.approx(0.05) and feats["focus_distance"] == pytest.approx(4.0)
    # Glass in a white furnace: energy is conserved up to noise.
    assert 0.5 < arrays["radiance"].mean() < 1.5


def test_variant_switched_elsewhere_is_restored(mi, cornell, settings) -> None:
    """Mitsuba's variant is process-global; a render after user code switched it still works."""
    from mcdenoise.render import render_samples
    from mcdenoise.render._mitsuba import VARIANT, mitsuba

    mi.set_variant("scalar_rgb")
    try:
        assert mitsuba().variant() == VARIANT
        arrays, _ = render_samples(cornell, settings, seed=1)
        assert arrays["radiance"].shape == (S, 3, H, W)
    finally:
        mitsuba()
