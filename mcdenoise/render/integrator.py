"""Our path tracer: a Python ``mi.SamplingIntegrator`` that records per-sample features.

It traces exactly the same paths as its plain ``sample()`` (used by ``mi.render``): feature
recording only adds loop state and never consumes random numbers, so the per-sample radiance is
bit-identical to what ``mi.render`` accumulates. The estimator is Mitsuba's own unidirectional path
tracer (emitter sampling + BSDF sampling, power-heuristic MIS, Russian roulette from ``rr_depth``)
with Mitsuba's ``max_depth`` convention (1 = directly visible emitters only).

Recording levels (``trace(..., level=)``):

* ``LEVEL_RADIANCE`` (0): radiance only; what ``mi.render`` calls.
* ``LEVEL_REFERENCE`` (1): radiance, its diffuse part, first-hit albedo (cheap; for references).
* ``LEVEL_FULL`` (2): every per-sample channel of :mod:`mcdenoise.render.channels_spec`.

Diffuse / specular split (per sample, so the parts always sum to the total): the path is classified
at its first vertex whose BSDF sampling picked a non-delta lobe, by the lobe it picked (diffuse ->
diffuse; glossy -> specular). Mitsuba's principled BSDF ignores the lobe mask in ``eval()``, so the
sampled lobe is the only reliable classifier. Light gathered before that vertex (emitters seen
directly or through delta bounces) counts as specular; light gathered from that vertex on (its own
emitter sample included) goes to the class it decided.

Mitsuba is imported lazily: :func:`register` builds the class on first use.
"""

from __future__ import annotations

from typing import Any

from mcdenoise.render.emitter_order import sample_emitter_direction as _ordered_emitter_direction

__all__ = [
    "INTEGRATOR_NAME",
    "LEVEL_RADIANCE",
    "LEVEL_REFERENCE",
    "LEVEL_FULL",
    "register",
    "integrator_class",
    "FULL_OUTPUTS",
]

INTEGRATOR_NAME = "mcdenoise_path"
LEVEL_RADIANCE = 0
LEVEL_REFERENCE = 1
LEVEL_FULL = 2
LOBE_VERTICES = 3

#: Names and component counts of the per-sample outputs of ``trace(level=LEVEL_FULL)``.
FULL_OUTPUTS: dict[str, int] = {
    "radiance": 3,
    "diffuse": 3,
    "specular": 3,
    "albedo": 3,
    "normal": 3,
    "depth": 1,
    "position": 3,
    "albedo_diffuse": 3,
    "normal_diffuse": 3,
    "depth_diffuse": 1,
    "roughness": 1,
    "visibility": 1,
    "lobes": 5 * LOBE_VERTICES,
    "path_length": 1,
}

_CLASS: Any = None
# Set by register(): dr.syntax re-executes the traced function in module globals, so the lazily
# imported modules must live here rather than in a closure.
mi: Any = None
dr: Any = None


def _mis_weight(pdf_a: Any, pdf_b: Any) -> Any:
    # Power heuristic; 0 where both pdfs vanish (inf/inf or 0/0).
    a2 = dr.square(pdf_a)
    w = a2 / (a2 + dr.square(pdf_b))
    return dr.select(dr.isfinite(w), w, 0.0)


def integrator_class() -> Any:
    """The integrator class (builds and registers it on first call)."""
    register()
    return _CLASS


def register() -> None:
    """Define the class and register it with Mitsuba as ``mcdenoise_path`` (idempotent)."""
    global _CLASS, mi, dr
    if _CLASS is not None:
        return
    import drjit as _dr
    import mitsuba as _mi

    mi, dr = _mi, _dr

    class McPathIntegrator(mi.SamplingIntegrator):
        """Path tracer with per-sample feature recording (see module docstring)."""

        def __init__(self, props: Any) -> None:
            super().__init__(props)
            self.max_depth = int(props.get("max_depth", 6))
            self.rr_depth = int(props.get("rr_depth", 5))
            if self.max_depth < 1:
                raise ValueError("mcdenoise_path: max_depth must be >= 1")
            # BSDF registry id -> GGX alpha; filled by the renderer per scene (None = unknown: 0).
            self.roughness_table: Any = None
            # (perm, distribution) of a canonical emitter order; set by the renderer for scenes
            # whose emitter list Mitsuba shuffles between loads (emitter_order.py). None: Mitsuba's.
            self.emitter_order: Any = None

        def aov_names(self) -> list[str]:
            return []

        def sample(self, scene: Any, sampler: Any, ray: Any, medium: Any = None, active: Any = True) -> Any:
            out = self.trace(scene, sampler, ray, active, LEVEL_RADIANCE)
            return out["radiance"], out["valid"], []

        @dr.syntax
        def trace(self, scene: Any, sampler: Any, ray_: Any, active_: Any, level: int) -> dict[str, Any]:
            """Trace one path per lane. Returns a dict of per-lane Dr.Jit values (see FULL_OUTPUTS)."""
            rec = level >= LEVEL_REFERENCE
            full = level >= LEVEL_FULL
            bsdf_ctx = mi.BSDFContext()
            ray = mi.Ray3f(dr.detach(ray_))
            depth = mi.UInt32(0)
            L = mi.Spectrum(0.0)
            beta = mi.Spectrum(1.0)
            eta = mi.Float(1.0)
            active = mi.Bool(active_)
            valid = mi.Bool(scene.environment() is not None)
            prev_si = dr.zeros(mi.Interaction3f)
            prev_bsdf_pdf = mi.Float(1.0)
            prev_bsdf_delta = mi.Bool(True)

            # Feature state. Unused ones stay constant and cost nothing in the compiled loop.
            L_diff = mi.Spectrum(0.0)
            decided = mi.Bool(False)
            is_diff = mi.Bool(False)
            albedo = mi.Color3f(0.0)
            normal = mi.Vector3f(0.0)
            hit_t = mi.Float(0.0)
            albedo_d = mi.Color3f(0.0)
            normal_d = mi.Vector3f(0.0)
            depth_d = mi.Float(0.0)
            found_d = mi.Bool(False)
            visibility = mi.Float(0.0)
            roughness = mi.Float(0.0)
            dist = mi.Float(0.0)
            # Sampled lobe flags of vertices 1..3, 8 bits each (BSDFFlags fit in the low byte
            # for the five flags we keep): one loop variable instead of three.
            lobes_packed = mi.UInt32(0)

            while dr.hint(active, max_iterations=self.max_depth, label="mcdenoise_path"):
                si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=(depth == 0))
                first = depth == 0

                # Emitter hit by the previous BSDF sample (or by the camera ray).
                ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
                em_pdf = scene.pdf_emitter_direction(prev_si, ds, ~prev_bsdf_delta)
                mis_bsdf = _mis_weight(prev_bsdf_pdf, em_pdf)
                Le = beta * mis_bsdf * ds.emitter.eval(si, prev_bsdf_pdf > 0.0)

                active_next = (depth + 1 < self.max_depth) & si.is_valid()
                bsdf = si.bsdf(ray)

                # Emitter sampling.
                active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
                if dr.hint(self.emitter_order is not None, mode="scalar"):
                    ds_em, em_weight = _ordered_emitter_direction(mi, dr, scene, si, sampler.next_2d(), active_em,
                                                                  *self.emitter_order)
                else:
                    ds_em, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, active_em)
                active_em &= ds_em.pdf != 0.0
                wo = si.to_local(ds_em.d)
                bsdf_val_em, bsdf_pdf_em = bsdf.eval_pdf(bsdf_ctx, si, wo, active_em)
                mis_em = dr.select(ds_em.delta, 1.0, _mis_weight(ds_em.pdf, bsdf_pdf_em))
                Lr_dir = beta * mis_em * bsdf_val_em * em_weight

                # BSDF sampling.
                bsdf_sample, bsdf_weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)

                if dr.hint(rec, mode="scalar"):
                    # The lobe sampling picked; a failed sample falls back to the BSDF's flags so
                    # that its emitter-sampling contribution is still classified.
                    lobe = dr.select(bsdf_sample.sampled_type == 0, bsdf.flags(), bsdf_sample.sampled_type)
                    lobe = dr.select(active_next, lobe, mi.UInt32(0))
                    lobe_diffuse = mi.has_flag(lobe, mi.BSDFFlags.Diffuse)
                    # Emission seen on arrival belongs to the class decided before this vertex.
                    L_diff[decided & is_diff] += Le
                    newly = active_next & ~decided & ~mi.has_flag(lobe, mi.BSDFFlags.Delta) & (lobe != 0)
                    is_diff[newly] = lobe_diffuse
                    decided |= newly
                    L_diff[decided & is_diff] += Lr_dir

                    hit_first = first & si.is_valid()
                    # One diffuse-reflectance evaluation per vertex serves both albedo records.
                    refl_mask = hit_first
                    if dr.hint(full, mode="scalar"):
                        new_d = active_next & ~found_d & lobe_diffuse
                        refl_mask = hit_first | new_d
                    refl = dr.clip(bsdf.eval_diffuse_reflectance(si, refl_mask), 0.0, 1.0)
                    bsdf_is_diffuse = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Diffuse)
                    # Purely specular/glossy materials: their tint (sampled weight, clamped to [0,1]).
                    albedo[hit_first] = dr.select(bsdf_is_diffuse, refl, dr.clip(bsdf_weight, 0.0, 1.0))

                if dr.hint(full, mode="scalar"):
                    hit_first = first & si.is_valid()
                    normal[hit_first] = si.sh_frame.n
                    hit_t[hit_first] = si.t
                    dist[si.is_valid()] += si.t
                    if dr.hint(self.roughness_table is not None, mode="scalar"):
                        bid = dr.reinterpret_array(mi.UInt32, bsdf)
                        # BSDFs the table does not know (e.g. inside instances) read as 0.
                        known = hit_first & (bid < dr.width(self.roughness_table))
                        rough = dr.gather(mi.Float, self.roughness_table, bid, known)
                        roughness[hit_first] = rough
                    albedo_d[new_d] = refl
                    normal_d[new_d] = si.sh_frame.n
                    depth_d[new_d] = dist
                    visibility[new_d] = dr.select(active_em & (dr.max(em_weight) > 0.0), 1.0, 0.0)
                    found_d |= new_d
                    small = (
                        dr.select(mi.has_flag(lobe, mi.BSDFFlags.Reflection), 1, 0)
                        | dr.select(mi.has_flag(lobe, mi.BSDFFlags.Transmission), 2, 0)
                        | dr.select(mi.has_flag(lobe, mi.BSDFFlags.Diffuse), 4, 0)
                        | dr.select(mi.has_flag(lobe, mi.BSDFFlags.Glossy), 8, 0)
                        | dr.select(mi.has_flag(lobe, mi.BSDFFlags.Delta), 16, 0)
                    )
                    at_v = active_next & (depth < LOBE_VERTICES)
                    lobes_packed[at_v] = lobes_packed | (mi.UInt32(small) << (depth * 8))

                L = L + Le + Lr_dir
                ray = si.spawn_ray(si.to_world(bsdf_sample.wo))
                eta *= bsdf_sample.eta
                beta *= bsdf_weight
                valid |= active & si.is_valid() & ~mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Null)

                prev_si = mi.Interaction3f(si)
                prev_bsdf_pdf = bsdf_sample.pdf
                prev_bsdf_delta = mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Delta)

                # Russian roulette, as Mitsuba's path tracer does it.
                beta_max = dr.max(beta)
                active_next &= beta_max != 0.0
                rr_prob = dr.minimum(beta_max * dr.square(eta), 0.95)
                rr_active = depth >= self.rr_depth
                beta[rr_active] *= dr.rcp(rr_prob)
                rr_continue = sampler.next_1d() < rr_prob
                active_next &= ~rr_active | rr_continue

                depth[si.is_valid()] += 1
                active = active_next

            out: dict[str, Any] = {"radiance": L, "valid": valid}
            if dr.hint(rec, mode="scalar"):
                out["diffuse"] = L_diff
                out["specular"] = L - L_diff
                out["albedo"] = albedo
            if dr.hint(full, mode="scalar"):
                out["normal"] = normal
                out["depth"] = hit_t
                # From the camera ray rather than a loop variable: fewer live values in the loop.
                out["position"] = dr.select(hit_t > 0.0, ray_.o + ray_.d * hit_t, 0.0)
                out["albedo_diffuse"] = albedo_d
                out["normal_diffuse"] = normal_d
                out["depth_diffuse"] = depth_d
                out["roughness"] = roughness
                out["visibility"] = visibility
                out["lobes"] = [
                    dr.select((lobes_packed & (1 << (8 * v + j))) != 0, 1.0, 0.0)
                    for v in range(LOBE_VERTICES)
                    for j in range(5)
                ]
                out["path_length"] = mi.Float(depth)
            return out

        def to_string(self) -> str:
            return f"McPathIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}]"

    mi.register_integrator(INTEGRATOR_NAME, lambda props: McPathIntegrator(props))
    _CLASS = McPathIntegrator
