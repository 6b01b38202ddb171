"""The ``haze`` integrator: volpath's light transport for one homogeneous medium in a sphere, without its overhead.

The simulation scene of a frame in fog, rain or snow holds one homogeneous,
isotropic, grey medium filling a sphere around the camera and the object
(:mod:`undream.scene.mitsuba_scene`). Mitsuba's ``volpath`` renders it through a
null-surfaced sphere shape and the medium's plugin: on the CPU every bounce then
pays for the medium's virtual calls and the boundary's extra intersections: on the same
frame with no medium at all ``volpath`` cost 2.7× ``path`` (docs/performance.md, "Media: the haze
integrator").

``haze`` computes the same estimator with the medium written out: the sphere is
intersected analytically (no shape, so shadow rays do not stop at it), the
free-flight distance is sampled from ``σt`` directly, and the transmittance
along a shadow ray is ``exp(−σt · length inside the sphere)`` (volpath's
delta-tracking estimate of it has this expectation). Everything else is as
volpath does it: next-event estimation at surfaces and in the medium with MIS
against the BSDF and the isotropic phase function, emitters hit by BSDF or phase
sampling weighted by MIS, Russian roulette after ``rr_depth`` and ``max_depth``
counted over surface and medium scattering alike. Its images have volpath's
expectation (tests/test_haze.py compares them pixel by pixel); their noise differs. Each vertex of a
path, in the medium or on a surface, draws one light sample and traces one shadow ray: a vectorised
loop pays for both branches of every iteration, so two (one per kind of vertex) cost 11–22 % more
kernel time on the 16-condition job's snow frames for the same samples (docs/performance.md). A frame in haze
still costs more than a clear one: most of its sky pixels' rays scatter in the medium and go on
bouncing, where a clear frame's end at the sky (4.3 vertices a path against 2.0).

Parameters (the scene adapter writes them): ``sigma_t`` (1/m), ``albedo`` (RGB,
``σs/σt``), ``center`` and ``radius`` (m) of the medium's sphere, ``max_depth``,
``rr_depth``. The camera may be inside or outside the sphere.
"""
from __future__ import annotations

import math
from types import ModuleType

NAME = "haze"
INV_FOUR_PI = 1.0 / (4.0 * math.pi)  # the isotropic phase function's value and pdf
_classes: dict[str, type] = {}  # the integrator's class per Mitsuba variant it is registered in


def register(mi: ModuleType) -> None:
    """Register the ``haze`` integrator with ``mi``'s current variant (once per variant)."""
    variant = mi.variant()
    if variant is None or variant in _classes:
        return
    cls = _classes[variant] = _integrator_class(mi)
    mi.register_integrator(NAME, lambda props: cls(props))


def _integrator_class(mi: ModuleType) -> type:
    import drjit as dr
    from mitsuba.ad.integrators.common import mis_weight

    # @dr.syntax compiles ``sample`` again from its source, with this module's globals and no closure:
    # the names it uses must be found there
    globals().update(mi=mi, dr=dr, mis_weight=mis_weight)

    class HazeIntegrator(mi.SamplingIntegrator):  # type: ignore[misc, name-defined]
        def __init__(self, props):
            super().__init__(props)
            self.max_depth = props.get("max_depth", 6)
            self.rr_depth = props.get("rr_depth", 5)
            if self.max_depth < 0:
                self.max_depth = 2**31 - 1
            sigma_t, radius = float(props.get("sigma_t")), float(props.get("radius"))
            if not (sigma_t > 0.0 and radius > 0.0):
                raise ValueError(f"haze: sigma_t and radius must be > 0, got {sigma_t} and {radius}")
            # Dr.Jit values, traversed: a scene cache writes another frame's medium into them
            self.sigma_t = mi.Float(sigma_t)
            self.albedo = mi.Color3f(props.get("albedo"))
            self.center = mi.Point3f(props.get("center"))
            self.radius = mi.Float(radius)

        def traverse(self, callback):
            for name in ("sigma_t", "albedo", "center", "radius"):
                callback.put(name, getattr(self, name), mi.ParamFlags.NonDifferentiable)

        def parameters_changed(self, keys):
            pass  # read when a render is traced: nothing is derived from them

        def _segment(self, o, d):
            """Whether the line o + t·d meets the sphere, and where inside it (t ≥ 0); ``d`` unit."""
            oc = o - self.center
            b = dr.dot(oc, d)
            disc = b * b - (dr.squared_norm(oc) - self.radius * self.radius)
            s = dr.safe_sqrt(disc)
            return disc > 0.0, dr.maximum(-b - s, 0.0), -b + s

        def _transmittance(self, ray):
            meets, enter, leave = self._segment(ray.o, ray.d)
            inside = dr.maximum(dr.minimum(leave, ray.maxt) - enter, 0.0)
            return dr.select(meets, dr.exp(-self.sigma_t * inside), 1.0)

        @dr.syntax
        def sample(self, scene, sampler, ray_, medium=None, active=True):
            ray = mi.Ray3f(ray_)
            active = mi.Bool(active)
            depth = mi.UInt32(0)
            throughput = mi.Spectrum(1.0)
            result = mi.Spectrum(0.0)
            specular_chain = mi.Bool(active)
            last_event = dr.zeros(mi.Interaction3f)
            last_pdf = mi.Float(1.0)
            valid_ray = mi.Bool(scene.environment() is not None)
            ctx = mi.BSDFContext()
            while active:
                # Russian roulette and the depth limit, where volpath has them
                q = dr.minimum(dr.max(throughput), 0.95)
                roulette = depth > self.rr_depth
                active &= (sampler.next_1d(active) < q) | ~roulette
                throughput[roulette] *= dr.rcp(q)
                active &= depth < self.max_depth

                # a free flight through the medium up to the next surface (or out of the sphere)
                si = scene.ray_intersect(ray, active)
                meets, enter, leave = self._segment(ray.o, ray.d)
                leave = dr.minimum(leave, dr.select(si.is_valid(), si.t, dr.inf))
                crossing = active & meets & (leave > enter)
                t = enter - dr.log(1.0 - sampler.next_1d(crossing)) / self.sigma_t
                scatter = crossing & (t < leave)
                depth[scatter] += 1
                active &= depth < self.max_depth
                surface = active & ~scatter
                scatter &= active

                # an emitter hit (the sky on a miss), weighted against next-event estimation
                count_direct = (depth == 0) | specular_chain
                emitter = si.emitter(scene)
                hit_e = surface & (emitter != None)  # noqa: E711 (a Dr.Jit pointer array compares element-wise)
                ds = mi.DirectionSample3f(scene, si, last_event)
                emitter_pdf = scene.pdf_emitter_direction(last_event, ds, hit_e & ~count_direct)
                weight = dr.select(count_direct, 1.0, mis_weight(last_pdf, emitter_pdf))
                result[hit_e] += throughput * emitter.eval(si, hit_e) * weight

                # the vertex: a surface or a point of the medium (no normal: its rays are not offset).
                # One light sample and one shadow ray serve either, where volpath pays for both
                surface &= si.is_valid()
                throughput[scatter] *= self.albedo
                vertex = mi.Interaction3f(si)
                vertex.p = dr.select(scatter, ray(t), si.p)
                vertex.n = dr.select(scatter, 0.0, si.n)
                vertex.t = dr.select(scatter, t, si.t)
                vertex.time, vertex.wavelengths = ray.time, ray.wavelengths
                bsdf = si.bsdf(ray)
                nee = scatter | (surface & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
                                 & (depth + 1 < self.max_depth))
                ds_e, emitted = scene.sample_emitter_direction(vertex, sampler.next_2d(nee), False, nee)
                shadow = vertex.spawn_ray_to(ds_e.p)
                lit = nee & (ds_e.pdf > 0.0)
                lit &= ~scene.ray_test(shadow, lit)
                bsdf_val, bsdf_pdf = bsdf.eval_pdf(ctx, si, si.to_local(ds_e.d), lit & surface)
                f_val = dr.select(scatter, INV_FOUR_PI, bsdf_val)
                f_pdf = dr.select(scatter, INV_FOUR_PI, bsdf_pdf)
                w_e = mis_weight(ds_e.pdf, dr.select(ds_e.delta, 0.0, f_pdf))
                result[lit] += throughput * f_val * emitted * self._transmittance(shadow) * w_e

                # the next direction: from the isotropic phase function or from the BSDF
                bs, bsdf_weight = bsdf.sample(ctx, si, sampler.next_1d(surface), sampler.next_2d(surface), surface)
                phase_d = mi.warp.square_to_uniform_sphere(sampler.next_2d(scatter))
                throughput[surface] *= bsdf_weight
                moving = surface | scatter
                ray[moving] = vertex.spawn_ray(dr.select(scatter, phase_d, si.to_world(bs.wo)))
                depth[surface] += 1
                last_event[moving] = vertex
                last_pdf[moving] = dr.select(scatter, INV_FOUR_PI, bs.pdf)
                valid_ray |= moving
                specular_chain &= ~scatter
                specular_chain |= surface & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
                specular_chain &= ~(surface & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Smooth))
                active &= moving & dr.any(throughput != 0.0)
            return result, valid_ray, []

        def to_string(self):
            return f"HazeIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}]"

    return HazeIntegrator
