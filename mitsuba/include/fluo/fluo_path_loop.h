// The path loop of the fluo_path integrator, written once for both of its transports.
//
// FluoPathLoop is a scalar port of Mitsuba's path.cpp (v3.8.0): camera ray, emitter
// hits with MIS, next-event estimation, BSDF sampling, Russian roulette, max_depth,
// rr_depth and hide_emitters exactly as `path`, plus the resolution of the BSDF
// wrappers around fluorescent materials (fluo_path_scene.h). What a path carries and
// what a vertex does to it is left to a transport's `Path`, which the loop calls at
// fixed points; the random numbers the loop draws, and their order, are the same for
// every transport:
//
//   Vertex begin_vertex(const BSDF *bsdf, SurfaceInteraction3f &si, Sampler *sampler)
//       The material at a surface vertex, before emitter sampling. May draw random
//       numbers and change si.wavelengths (spectral: the wavelength shifts).
//   void on_emission(const Emitter *emitter, const Spectrum &radiance, Float mis)
//       A BSDF-sampled ray (or the camera ray) hit an emitter.
//   BSDFSample3f scatter(const Vertex &v, const BSDF *bsdf, const SurfaceInteraction3f &si,
//                        const EmitterSample &em, Float sample1, const Point2f &sample2)
//       Add the emitter sample's contribution (when em.active), sample the BSDF with
//       (sample1, sample2), multiply the throughput by the sample's weight, and return
//       the sample.
//   double throughput_max() const   the throughput's size for Russian roulette
//   void roulette(Float rr_prob)    divide the throughput by the survival probability
//   Spectrum radiance() const       the sample's value once the path ends
//
// The transports: fluo_transport_spectral.h (Mitsuba's RGB or spectral throughput,
// with wavelength shifting) and fluo_transport_reduced.h (scalar_rgb: matrix throughput).
#pragma once

#include <mitsuba/core/properties.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/emitter.h>
#include <mitsuba/render/integrator.h>
#include <mitsuba/render/records.h>

#include <utility>

#include "fluo_path_scene.h"

NAMESPACE_BEGIN(mitsuba)
NAMESPACE_BEGIN(fluo_detail)

/// Power heuristic, as in path.cpp (non-finite weights become 0).
template <typename Float> Float mis_weight(Float pdf_a, Float pdf_b) {
    pdf_a *= pdf_a;
    pdf_b *= pdf_b;
    Float w = pdf_a / (pdf_a + pdf_b);
    return dr::select(dr::isfinite(w), w, 0.f);
}

/// mis_weight without gradients (the vectorised integrators' MIS weights).
template <typename Float> Float detached_mis_weight(const Float &pdf_a, const Float &pdf_b) {
    return dr::detach<true>(mis_weight(pdf_a, pdf_b));
}

/// Next-event estimation at a vertex: the emitter sample, valid when `active`
/// (the BSDF is smooth and the sample has a positive pdf). `wo` is the sample's
/// direction in the local frame (zero when no emitter was sampled).
template <typename Float, typename Spectrum> struct EmitterSample {
    MI_IMPORT_TYPES()
    Mask active = false;
    DirectionSample3f ds = dr::zeros<DirectionSample3f>();
    Spectrum weight = dr::zeros<Spectrum>();
    Vector3f wo = dr::zeros<Vector3f>();
};

NAMESPACE_END(fluo_detail)

/// Mitsuba's MonteCarloIntegrator with fluo_path's path loop (see the file comment).
template <typename Float, typename Spectrum>
class FluoPathLoop : public MonteCarloIntegrator<Float, Spectrum> {
public:
    MI_IMPORT_BASE(MonteCarloIntegrator, m_max_depth, m_rr_depth, m_hide_emitters)
    MI_IMPORT_TYPES(Scene, Sampler, Emitter, BSDFPtr)
    using EmitterSample = fluo_detail::EmitterSample<Float, Spectrum>;

protected:
    explicit FluoPathLoop(const Properties &props) : Base(props) {}

    /// One camera path, its transport state and events in `path`.
    template <typename Path>
    std::pair<Spectrum, Bool> trace(const Scene *scene, Sampler *sampler, const RayDifferential3f &ray_,
                                    Bool active, Path &path) const {
        if (unlikely(m_max_depth == 0))
            return { 0.f, false };

        Ray3f ray              = Ray3f(ray_);
        Float eta              = 1.f;
        UInt32 depth           = 0;
        Mask valid_ray         = !m_hide_emitters && (scene->environment() != nullptr);
        Interaction3f prev_si  = dr::zeros<Interaction3f>();
        Float prev_bsdf_pdf    = 1.f;
        Bool prev_bsdf_delta   = true;

        PreliminaryIntersection3f pi = camera_intersection(scene, ray, active);

        while (active) {
            SurfaceInteraction3f si = pi.compute_surface_interaction(ray, +RayFlags::All);

            // ---------------------- Direct emission ----------------------
            if (si.emitter(scene) != nullptr) {
                auto [emitter, le, mis_bsdf] = hit_emission(scene, si, prev_si, prev_bsdf_pdf, prev_bsdf_delta);
                path.on_emission(emitter, le, mis_bsdf);
            }

            Bool active_next = (depth + 1 < m_max_depth) && si.is_valid();
            if (!active_next) {
                valid_ray |= (si.emitter(scene) != nullptr) && !m_hide_emitters;
                break;
            }

            BSDFPtr bsdf = si.bsdf(ray);
            typename fluo_detail::FluoWrappers<Float, Spectrum>::Perturbations perturbed;
            if (!m_wrappers.empty())
                bsdf = m_wrappers.resolve(bsdf, si, sampler, perturbed);
            auto vertex = path.begin_vertex(bsdf, si, sampler);

            // ---------------------- Emitter sampling ----------------------
            EmitterSample em;
            em.active = active_next && has_flag(bsdf->flags(), BSDFFlags::Smooth);
            if (em.active) {
                std::tie(em.ds, em.weight) = scene->sample_emitter_direction(si, sampler->next_2d(), true, em.active);
                em.active &= (em.ds.pdf != 0.f) && perturbed.keeps_side(em.ds.d);
                em.wo = si.to_local(em.ds.d);
            }

            // ------------- Emitter contribution, BSDF sampling -------------
            Float sample_1 = sampler->next_1d();
            Point2f sample_2 = sampler->next_2d();
            BSDFSample3f bs = path.scatter(vertex, bsdf, si, em, sample_1, sample_2);

            ray = si.spawn_ray(si.to_world(bs.wo)); // carries shifted wavelengths, if any
            eta *= bs.eta;
            valid_ray |= active && si.is_valid() && !has_flag(bs.sampled_type, BSDFFlags::Null);
            if (!perturbed.keeps_side(ray.d)) // a normal or bump map's sample across the surface: no weight
                break;

            prev_si = Interaction3f(si);
            prev_bsdf_pdf = bs.pdf;
            prev_bsdf_delta = has_flag(bs.sampled_type, BSDFFlags::Delta);

            // -------------------- Stopping criterion ---------------------
            if (si.is_valid())
                depth += 1;
            double throughput_max = path.throughput_max();
            Float rr_prob = dr::minimum((Float) throughput_max * dr::square(eta), .95f);
            Mask rr_active = depth >= m_rr_depth, rr_continue = sampler->next_1d() < rr_prob;
            if (rr_active)
                path.roulette(rr_prob);
            active = active_next && (!rr_active || rr_continue) && (throughput_max != 0.0);

            pi = scene->ray_intersect_preliminary(ray, false, false, 0, 0, active);
        }

        return { dr::select(valid_ray, path.radiance(), 0.f), valid_ray };
    }

    /// The wrappers around fluorescent materials, found by a transport's prepare().
    fluo_detail::FluoWrappers<Float, Spectrum> m_wrappers;

private:
    /// First intersection of a camera ray, skipping area emitters when they are hidden
    /// (as path.cpp does at depth 0).
    PreliminaryIntersection3f camera_intersection(const Scene *scene, const Ray3f &ray, Mask active) const {
        PreliminaryIntersection3f pi = scene->ray_intersect_preliminary(ray, true, false, 0, 0, active);
        if (m_hide_emitters) {
            Mask skip = pi.is_valid() && (pi.shape->emitter() != nullptr) && active;
            if (skip) {
                SurfaceInteraction3f si = pi.compute_surface_interaction(ray, +RayFlags::Minimal, skip);
                pi = Base::skip_area_emitters(scene, si.spawn_ray(ray.d), true, skip);
            }
        }
        return pi;
    }

    /// Emission found by a BSDF-sampled ray: (emitter, radiance, MIS weight), as in path.cpp.
    std::tuple<const Emitter *, Spectrum, Float>
    hit_emission(const Scene *scene, const SurfaceInteraction3f &si, const Interaction3f &prev_si,
                 Float prev_bsdf_pdf, Bool prev_bsdf_delta) const {
        DirectionSample3f ds(scene, si, prev_si);
        Float em_pdf = 0.f;
        if (!prev_bsdf_delta)
            em_pdf = scene->pdf_emitter_direction(prev_si, ds, !prev_bsdf_delta);
        return { ds.emitter, ds.emitter->eval(si, prev_bsdf_pdf > 0.f), fluo_detail::mis_weight(prev_bsdf_pdf, em_pdf) };
    }
};

NAMESPACE_END(mitsuba)
