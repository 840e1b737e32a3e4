"""View stacks (several cameras of one scene in one launch) against single-view renders."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.render

N, SPP = 16, 32


def _camera(scene) -> np.ndarray:
    from mcdenoise.render._mitsuba import mitsuba

    mi = mitsuba()
    return np.array(mi.Transform4f(mi.traverse(scene.sensors()[0])["to_world"]).matrix, dtype=np.float64).reshape(4, 4)


def _moved(c: np.ndarray, dx: float, yaw: float) -> np.ndarray:
    """``c`` moved sideways by ``dx`` and turned by ``yaw`` radians about its own up axis."""
    r = np.eye(4)
    r[0, 0] = r[2, 2] = np.cos(yaw)
    r[0, 2], r[2, 0] = np.sin(yaw), -np.sin(yaw)
    t = np.eye(4)
    t[0, 3] = dx
    return c @ t @ r


def _stack(scene, settings, cams, seed=3):
    from mcdenoise.render.procedural.views import set_camera
    from mcdenoise.render.view_stack import render_view_stack

    base = _camera(scene)
    set_camera(scene, base)
    out = render_view_stack(scene, settings, cams, base, seed=seed)
    assert all(np.isfinite(o["radiance"]).all() for o in out)
    return out


def _close(a: dict, b: dict) -> tuple[float, float]:
    """(median relative difference of the per-pixel mean depth, mean absolute difference of the
    per-pixel mean albedo) of two renders, each from its own samples. First-hit features: the
    radiance's mean differs by 5-10% between two seeds of one view here (fireflies)."""
    da, db = a["depth"].mean(axis=0)[0], b["depth"].mean(axis=0)[0]
    depth = float(np.median(np.abs(da - db) / np.maximum(db, 1e-3)))
    return depth, float(np.abs(a["albedo"].mean(axis=0) - b["albedo"].mean(axis=0)).mean())


@pytest.mark.parametrize("name", ["cornell-box", "cornell-motion", "cornell-camera-motion"])
def test_a_stacked_view_is_the_view_rendered_alone(mi, name: str) -> None:
    """Catches: the stack's rays not moved to their own view (or by the inverse transform, or to
    another view's), stacked rows cut at the wrong view boundary, a moving camera or moving objects
    breaking either, and views of a stack not sharing their time slices. A view in a stack has
    other samples than alone, so the renders are compared through first-hit features. Measured at
    16x16, 32 spp on these scenes: the same view differs by at most 0.9% (median depth) and 0.019
    (mean albedo), another view by at least 19% and 0.29; the bounds sit 3x above the former."""
    from dataclasses import replace

    from mcdenoise.render import RenderSettings, builtin_motion, load_scene, render_samples

    scene = load_scene(name, width=N, height=N)
    motion = builtin_motion(name)
    st = RenderSettings(spp=SPP, ref_spp=0, width=N, height=N, seed=1, **motion)
    base = _camera(scene)
    cams = [_moved(base, 0.4, 0.15), base, _moved(base, -0.3, -0.1)]
    stacked = _stack(scene, st, cams)
    for v, cam in enumerate(cams):
        end = None
        if st.camera_to_world_end is not None:  # the sensor's motion, in this view's camera space
            end = cam @ np.linalg.inv(base) @ st.camera_to_world_end
        alone, _ = render_samples(scene, replace(st, seed=10 + v, camera_to_world_end=end), camera_to_world=cam)
        depth, albedo = _close(stacked[v], alone)
        assert depth < 0.03 and albedo < 0.06, (name, v, depth, albedo)
        other = cams[(v + 1) % len(cams)]
        alone_other, _ = render_samples(scene, replace(st, seed=20 + v, camera_to_world_end=None if end is None else
                                                       other @ np.linalg.inv(base) @ st.camera_to_world_end),
                                        camera_to_world=other)
        assert _close(stacked[v], alone_other)[0] > 0.1  # the test tells cameras apart
    if st.object_motion:  # one time per sample index, shared by the views of the stack
        times = [s["time"][:, 0].reshape(SPP, -1) for s in stacked]
        assert np.ptp(times[0], axis=1).max() == 0 and np.array_equal(times[0], times[1])


def test_a_stack_is_deterministic_and_leaves_the_scene_as_loaded(mi) -> None:
    """Catches: a stack's samples depending on anything but its views and seed (a resumed dataset
    re-renders a missing view's stack and must get the same pixels), and the sensor or moving
    objects left posed afterwards."""
    from mcdenoise.render import RenderSettings, builtin_motion, load_scene, render_samples

    scene = load_scene("cornell-motion", width=N, height=N)
    st = RenderSettings(spp=4, ref_spp=0, width=N, height=N, seed=1, **builtin_motion("cornell-motion"))
    before, _ = render_samples(scene, st)
    base = _camera(scene)
    cams = [base, _moved(base, 0.2, 0.05)]
    a, b = _stack(scene, st, cams, seed=5), _stack(scene, st, cams, seed=5)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x["radiance"], y["radiance"])
    assert not np.array_equal(a[0]["radiance"], _stack(scene, st, cams, seed=6)[0]["radiance"])
    after, _ = render_samples(scene, st)
    np.testing.assert_array_equal(after["radiance"], before["radiance"])


def test_view_transforms_refuse_a_scaled_camera() -> None:
    """Catches: a camera with scale accepted (its rays' lengths, and so depth and position, would be wrong)."""
    from mcdenoise.errors import SceneError
    from mcdenoise.render.view_stack import view_transforms

    base = np.eye(4)
    m = view_transforms(base, [base, _moved(base, 1.0, 0.3)])
    assert m.shape == (24,) and np.allclose(m[:12].reshape(3, 4), np.eye(4)[:3])
    with pytest.raises(SceneError, match="view 1.*rigid"):
        view_transforms(base, [base, np.diag([2.0, 1.0, 1.0, 1.0])])


@pytest.mark.parametrize("name", ["cornell-box", "cornell-motion"])
def test_stacked_references_are_each_views_reference(mi, name: str) -> None:
    """Catches: stacked references cut at the wrong rows, not moved to their views, or posed at
    other times than the views' own references. Compared through the reference albedo (first hit,
    converged): at 16x16, 128 spp the same view's two references differ by at most 0.012 in mean
    albedo, another view's by 0.29 and more; bound 3x above the former. The image's mean radiance
    only as a check of scale (a stack summing or dividing per view wrongly): two seeds of one
    view differ by up to 17% here (the cornell box's fireflies), so its bound is 1.5x that."""
    from dataclasses import replace

    from mcdenoise.render import RenderSettings, builtin_motion, load_scene
    from mcdenoise.render.procedural.views import set_camera
    from mcdenoise.render.reference import render_reference

    scene = load_scene(name, width=N, height=N)
    st = RenderSettings(spp=1, ref_spp=128, width=N, height=N, seed=1, ref_time_slices=16, **builtin_motion(name))
    base = _camera(scene)
    cams = [_moved(base, 0.4, 0.15), base]
    set_camera(scene, base)
    refs = render_reference(scene, st, stack=(cams, base))
    assert len(refs) == 2
    for v, cam in enumerate(cams):
        alone = render_reference(scene, replace(st, seed=7 + v), camera_to_world=cam)
        other = render_reference(scene, replace(st, seed=9 + v), camera_to_world=cams[1 - v])
        albedo = float(np.abs(refs[v]["albedo"] - alone["albedo"]).mean())
        rad = float(abs(refs[v]["radiance"].mean() - alone["radiance"].mean()) / alone["radiance"].mean())
        assert albedo < 0.04 and rad < 0.26, (name, v, albedo, rad)
        assert float(np.abs(refs[v]["albedo"] - other["albedo"]).mean()) > 0.1


def test_stacked_checks_judge_each_views_own_camera(mi) -> None:
    """Catches: the stacked first-attempt checks of generator 4 measuring another view's camera
    (the object coverage is deterministic: it must agree with each camera's own mask), or
    accepting every camera. Scene 2 of the rich world at seed 7, 32x32: camera 0 of view 5 shows
    objects on 7% of the image and must be rejected."""
    from mcdenoise.render.dataset_config import DatasetConfig
    from mcdenoise.render.procedural import derive_seed, generate
    from mcdenoise.render.procedural.preview import object_mask
    from mcdenoise.render.procedural.views import set_camera, view_camera
    from mcdenoise.render.procedural_image import _settings, _stacked_checks, check_settings

    cfg = DatasetConfig(count=3, seed=7, spp=16, ref_spp=0, width=32, height=32, objects=(10, 20), world="rich",
                        max_depth=8, views=6)
    ss = derive_seed(7, 2)
    ps = generate(ss, width=32, height=32, objects=(10, 20), world="rich", keep_loaded=True, stack=True,
                  settings=lambda p: check_settings(cfg, _settings(cfg, 1, ps=p, camera=p.camera_to_world,
                                                                   camera_end=p.camera_to_world_end), first_view=True))
    views = list(range(1, 6))
    verdicts = _stacked_checks(cfg, ps, ss, views)
    for v in views:
        set_camera(ps.loaded, view_camera(ps, np.random.default_rng(derive_seed(ss, 3, v, 0))))
        low = object_mask(ps.loaded, 32, 32).mean() < 0.08
        assert low == ("objects cover" in (verdicts[v] or "")), (v, verdicts[v])
    assert "objects cover" in (verdicts[5] or "")


def test_a_stack_refuses_a_sampler_whose_lanes_are_ordered(mi) -> None:
    """Catches: a stratified or multi-jittered sampler accepted by a stack, whose sample-major lane
    order would hand each pixel another pixel's strata (the stack's samples must be interchangeable)."""
    from mcdenoise.errors import SceneError
    from mcdenoise.render import RenderSettings
    from mcdenoise.render.view_stack import iter_view_stack

    d = mi.load_dict({"type": "scene", "sensor": {"type": "perspective", "sampler": {"type": "stratified", "sample_count": 4},
                                                   "film": {"type": "hdrfilm", "width": 8, "height": 8}},
                      "s": {"type": "sphere"}})
    st = RenderSettings(spp=4, ref_spp=0, width=8, height=8)
    with pytest.raises(SceneError, match="independent"):
        next(iter_view_stack(d, st, [np.eye(4)], np.eye(4), seed=1))
