// fluo_path in the vectorised variants (llvm_ad_rgb, llvm_ad_spectral): Mitsuba's `path`
// loop (dr::while_loop, one kernel) with the same fluorescence as the scalar fluo_path
// (fluo_path.cpp documents the estimators and is the reference the tests hold this one
// against): per-lane wavelength shifting in spectral variants, the 3×K reduced matrix
// throughput in RGB ones. Fluorescent BSDFs are reached through dr::dispatch and the
// interface of fluo_jit.h; Rust runs once per render (the scene scan, reduced matrices).
#include <mitsuba/core/properties.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/emitter.h>
#include <mitsuba/render/integrator.h>
#include <mitsuba/render/records.h>
#include <mitsuba/render/scene.h>

#include <array>
#include <optional>
#include <sstream>
#include <string>
#include <unordered_map>
#include <vector>

#include "fluo_bispectral.h"
#include "fluo_common.h"
#include "fluo_jit.h"
#include "fluo_jit_reduced.h"
#include "fluo_path_loop.h"
#include "fluo_path_scene.h"

NAMESPACE_BEGIN(mitsuba)

template <typename Float, typename Spectrum>
class FluoPathJit final : public MonteCarloIntegrator<Float, Spectrum> {
public:
    MI_IMPORT_BASE(MonteCarloIntegrator, m_max_depth, m_rr_depth, m_hide_emitters)
    MI_IMPORT_TYPES(Scene, Sensor, Sampler, Medium, Emitter, EmitterPtr, BSDF, BSDFPtr, Shape, Texture)
    using Bispectral = fluo_detail::JitBispectral<Float, Spectrum>;
    using WMask = dr::mask_t<UnpolarizedSpectrum>;

    static constexpr const char *Plugin = "fluo_path";
    using Reduced = fluo_detail::JitReduced<Float, Spectrum>;

    FluoPathJit(const Properties &props)
        : Base(props), m_lambda_min(fluo_detail::lambda_min_of(Plugin, props)),
          m_reduced(Plugin, std::string(props.get<std::string_view>("basis", "x7")),
                    std::string(props.get<std::string_view>("method", "ours"))) {}

    using Base::render;
    TensorXf render(Scene *scene, Sensor *sensor, UInt32 seed, uint32_t spp, bool develop,
                    bool evaluate) override {
        prepare(scene);
        return Base::render(scene, sensor, seed, spp, develop, evaluate);
    }

    std::pair<Spectrum, Bool> sample(const Scene *scene, Sampler *sampler, const RayDifferential3f &ray,
                                     const Medium * /* medium */, Float * /* aovs */, Bool active) const override {
        if (unlikely(m_max_depth == 0))
            return { 0.f, false };
        if constexpr (is_rgb_v<Spectrum>) {
            if (m_reduced.size() > 0) {
                if (m_reduced.bands() == 3)
                    return sample_reduced<3>(scene, sampler, ray, active);
                if (m_reduced.bands() == 4)
                    return sample_reduced<4>(scene, sampler, ray, active);
                return sample_reduced<Reduced::KMax>(scene, sampler, ray, active);
            }
        }
        return sample_spectral(scene, sampler, ray, active);
    }

    std::string to_string() const override {
        std::ostringstream oss;
        oss << "FluoPath[" << std::endl
            << "  max_depth = " << m_max_depth << "," << std::endl
            << "  rr_depth = " << m_rr_depth << "," << std::endl
            << "  lambda_min = " << m_lambda_min << "," << std::endl
            << "  basis = " << m_reduced.name() << " (K = " << m_reduced.bands() << ")," << std::endl
            << "  fluorescent_bsdfs = " << m_bsdfs << "," << std::endl
            << "  excitation_range = [" << m_range_lo << ", " << m_range_hi << "]," << std::endl
            << "  variant = vectorised" << std::endl
            << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(FluoPathJit)

private:
    /// Once per render: the fluorescent BSDFs (refusing wrappers, which the vectorised
    /// loop cannot see through), the emitters' spectral range and, in RGB variants,
    /// reduced matrices and the emitters' basis coefficients.
    void prepare(Scene *scene) {
        fluo_detail::warn_if_media(Plugin, scene, m_media_warned);
        bool directional = false;
        fluo::Range lights = fluo_detail::emitters_range(scene);
        double lo = std::max(lights.lo, m_lambda_min), hi = lights.hi;
        std::vector<Bispectral *> bsdfs = fluo_detail::jit_fluorescent_bsdfs<Bispectral>(Plugin, scene);
        for (Bispectral *b : bsdfs) {
            hi = std::max(hi, b->jit_emission_range().hi); // re-emitted light can excite further shifts
            directional |= !b->jit_lambertian();
        }
        if (scene->emitters().empty())
            bsdfs.clear();
        m_reduced.prepare(scene, bsdfs, false);
        m_bsdfs = bsdfs.size();
        m_range_lo = lo;
        m_range_hi = hi;
        m_directional = directional && m_bsdfs > 0;
        m_varying = m_directional && m_reduced.varying();
    }

    /// First intersection of a camera ray, skipping area emitters when they are hidden
    /// (as path.cpp and the scalar fluo_path do at depth 0).
    PreliminaryIntersection3f camera_intersection(const Scene *scene, const Ray3f &ray, Mask active) const {
        PreliminaryIntersection3f pi = scene->ray_intersect_preliminary(ray, true, false, 0, 0, active);
        if (m_hide_emitters) {
            Mask skip = pi.is_valid() && (pi.shape->emitter() != nullptr) && active;
            if (dr::any_or<true>(skip)) {
                SurfaceInteraction3f si = pi.compute_surface_interaction(ray, +RayFlags::Minimal, skip);
                PreliminaryIntersection3f behind = Base::skip_area_emitters(scene, si.spawn_ray(ray.d), true, skip);
                pi = dr::select(skip, behind, pi);
            }
        }
        return pi;
    }

    /// Emission found by a BSDF-sampled ray (as path.cpp): emitter, radiance, MIS weight.
    template <typename State>
    std::tuple<EmitterPtr, Spectrum, Float> hit_emission(const Scene *scene, const SurfaceInteraction3f &si,
                                                         const State &ls) const {
        DirectionSample3f ds(scene, si, ls.prev_si);
        Float em_pdf = 0.f;
        if (dr::any_or<true>(!ls.prev_bsdf_delta))
            em_pdf = scene->pdf_emitter_direction(ls.prev_si, ds, !ls.prev_bsdf_delta);
        return { ds.emitter, ds.emitter->eval(si, ls.prev_bsdf_pdf > 0.f), mis_weight(ls.prev_bsdf_pdf, em_pdf) };
    }

    /// Next-event estimation at a vertex with a smooth BSDF (as path.cpp): the direction
    /// sample, the emitter's weight, the local direction and where the sample is valid.
    std::tuple<DirectionSample3f, Spectrum, Vector3f, Mask> sample_emitter(const Scene *scene,
                                                                           const SurfaceInteraction3f &si,
                                                                           Sampler *sampler, const BSDFPtr &bsdf,
                                                                           const Mask &active) const {
        Mask active_em = active && has_flag(bsdf->flags(), BSDFFlags::Smooth);
        DirectionSample3f ds = dr::zeros<DirectionSample3f>();
        Spectrum em_weight = dr::zeros<Spectrum>();
        Vector3f wo = dr::zeros<Vector3f>();
        if (dr::any_or<true>(active_em)) {
            std::tie(ds, em_weight) = scene->sample_emitter_direction(si, sampler->next_2d(), true, active_em);
            active_em &= (ds.pdf != 0.f);
            wo = si.to_local(ds.d);
        }
        return { ds, em_weight, wo, active_em };
    }

    /// The loop's bookkeeping after a BSDF sample (as path.cpp): the next ray, the alpha
    /// mask, the previous vertex for MIS, and the depth.
    template <typename State>
    static void advance(State &ls, const SurfaceInteraction3f &si, const BSDFSample3f &bs) {
        ls.ray = si.spawn_ray(si.to_world(bs.wo)); // carries the (shifted) wavelengths
        ls.eta *= bs.eta;
        ls.valid_ray |= ls.active && si.is_valid() && !has_flag(bs.sampled_type, BSDFFlags::Null);
        ls.prev_si = Interaction3f(si);
        ls.prev_bsdf_pdf = bs.pdf;
        ls.prev_bsdf_delta = has_flag(bs.sampled_type, BSDFFlags::Delta);
        dr::masked(ls.depth, si.is_valid()) += 1;
    }

    /// Russian roulette on `throughput_max` (as path.cpp): returns where the throughput must
    /// be scaled and by what, and ends the paths that stop.
    template <typename State>
    std::pair<Mask, Float> roulette(State &ls, const Float &throughput_max, const Mask &active_next) const {
        Float rr_prob = dr::minimum(throughput_max * dr::square(ls.eta), .95f);
        Mask rr_active = ls.depth >= m_rr_depth, rr_continue = ls.sampler->next_1d() < rr_prob;
        ls.active = active_next && (!rr_active || rr_continue) && (throughput_max != 0.f);
        return { rr_active, dr::rcp(dr::detach(rr_prob)) };
    }

    static Float mis_weight(const Float &a, const Float &b) { return fluo_detail::detached_mis_weight(a, b); }

    // ------------------------------------------------------------ spectral (and no fluorescence)
    struct LoopState {
        Ray3f ray;
        PreliminaryIntersection3f pi;
        Spectrum throughput, result;
        Float eta;
        UInt32 depth;
        Mask valid_ray;
        Interaction3f prev_si;
        Float prev_bsdf_pdf;
        Bool prev_bsdf_delta, active;
        Sampler *sampler;
        DRJIT_STRUCT(LoopState, ray, pi, throughput, result, eta, depth, valid_ray, prev_si, prev_bsdf_pdf,
                     prev_bsdf_delta, active, sampler)
    };

    std::pair<Spectrum, Bool> sample_spectral(const Scene *scene, Sampler *sampler, const RayDifferential3f &ray_,
                                              Bool active) const {
        LoopState ls = { Ray3f(ray_), dr::zeros<PreliminaryIntersection3f>(), Spectrum(1.f), Spectrum(0.f),
                         Float(1.f), UInt32(0), Mask(!m_hide_emitters && scene->environment() != nullptr),
                         dr::zeros<Interaction3f>(), Float(1.f), Bool(true), active, sampler };
        ls.pi = camera_intersection(scene, ls.ray, ls.active);
        const bool fluorescent = is_spectral_v<Spectrum> && m_bsdfs > 0, directional = m_directional;
        const double range_lo = m_range_lo, range_hi = m_range_hi;

        dr::tie(ls) = dr::while_loop(
            dr::make_tuple(ls), [](const LoopState &ls) { return ls.active; },
            [this, scene, fluorescent, directional, range_lo, range_hi](LoopState &ls) {
                BSDFContext bsdf_ctx;
                SurfaceInteraction3f si = ls.pi.compute_surface_interaction(ls.ray, +RayFlags::All);

                // ---------------------- Direct emission ----------------------
                if (dr::any_or<true>(si.emitter(scene) != nullptr)) {
                    auto [emitter, le, mis_bsdf] = hit_emission(scene, si, ls);
                    ls.result = dr::fmadd(ls.throughput, le * mis_bsdf, ls.result);
                }

                Bool active_next = (ls.depth + 1 < m_max_depth) && si.is_valid();
                if (dr::none_or<false>(active_next)) {
                    ls.active = active_next;
                    return;
                }
                BSDFPtr bsdf = si.bsdf(ls.ray);

                // ------- Fluorescence: per lane and hero wavelength, elastic or shift -------
                fluo_detail::JitSurfaceShift<Float, Spectrum> shift;
                if (fluorescent)
                    shift.choose(bsdf, si, ls.sampler, active_next, range_lo, range_hi);

                // ---------------------- Emitter sampling ----------------------
                auto [ds, em_weight, wo, active_em] = sample_emitter(scene, si, ls.sampler, bsdf, active_next);

                // ------ Evaluate BSDF * cos(theta) and sample direction -------
                Float sample_1 = ls.sampler->next_1d();
                Point2f sample_2 = ls.sampler->next_2d();
                auto [bsdf_val, bsdf_pdf, bsdf_sample, bsdf_weight] =
                    bsdf->eval_pdf_sample(bsdf_ctx, si, wo, sample_1, sample_2);

                if (fluorescent)
                    shift.apply(bsdf, si, directional, wo, bsdf_sample, active_next, bsdf_val, bsdf_weight);

                if (dr::any_or<true>(active_em)) {
                    Float mis_em = dr::select(ds.delta, 1.f, mis_weight(ds.pdf, bsdf_pdf));
                    ls.result[active_em] = dr::fmadd(ls.throughput, bsdf_val * em_weight * mis_em, ls.result);
                }

                // ---------------------- BSDF sampling ----------------------
                ls.throughput *= bsdf_weight;
                advance(ls, si, bsdf_sample);

                // -------------------- Stopping criterion ---------------------
                auto [rr_active, rr_scale] = roulette(ls, dr::max(unpolarized_spectrum(ls.throughput)), active_next);
                ls.throughput[rr_active] *= rr_scale;
                ls.pi = scene->ray_intersect_preliminary(ls.ray, false, false, 0, 0, ls.active);
            });

        return { dr::select(ls.valid_ray, ls.result, 0.f), ls.valid_ray };
    }

    // ------------------------------------------------------------ RGB: reduced transport
    template <size_t K> struct LoopStateR {
        Ray3f ray;
        PreliminaryIntersection3f pi;
        Color3f t;                 ///< RGB throughput until the first fluorescent vertex
        dr::Array<Float, 3 * K> R; ///< then the 3×K matrix throughput
        Mask reduced;
        Color3f result;
        Float eta;
        UInt32 depth;
        Mask valid_ray;
        Interaction3f prev_si;
        Float prev_bsdf_pdf;
        Bool prev_bsdf_delta, active;
        Sampler *sampler;
        DRJIT_STRUCT(LoopStateR, ray, pi, t, R, reduced, result, eta, depth, valid_ray, prev_si, prev_bsdf_pdf,
                     prev_bsdf_delta, active, sampler)
    };

    template <size_t K> using Coeffs = typename Reduced::template Coeffs<K>;
    template <size_t K> using Rows = typename Reduced::template Rows<K>;

    template <size_t K>
    std::pair<Spectrum, Bool> sample_reduced(const Scene *scene, Sampler *sampler, const RayDifferential3f &ray_,
                                             Bool active) const {
        if constexpr (!is_rgb_v<Spectrum>) {
            return { 0.f, false };
        } else {
            LoopStateR<K> ls = { Ray3f(ray_), dr::zeros<PreliminaryIntersection3f>(), Color3f(1.f),
                                 dr::zeros<Rows<K>>(), Mask(false), Color3f(0.f), Float(1.f), UInt32(0),
                                 Mask(!m_hide_emitters && scene->environment() != nullptr), dr::zeros<Interaction3f>(),
                                 Float(1.f), Bool(true), active, sampler };
            ls.pi = camera_intersection(scene, ls.ray, ls.active);

            dr::tie(ls) = dr::while_loop(
                dr::make_tuple(ls), [](const LoopStateR<K> &ls) { return ls.active; },
                [this, scene](LoopStateR<K> &ls) {
                    BSDFContext bsdf_ctx;
                    SurfaceInteraction3f si = ls.pi.compute_surface_interaction(ls.ray, +RayFlags::All);

                    if (dr::any_or<true>(si.emitter(scene) != nullptr)) {
                        auto [emitter, le, mis_bsdf] = hit_emission(scene, si, ls);
                        Color3f c =
                            m_reduced.template through<K>(ls.R, ls.t, ls.reduced, emitter, le, emitter != nullptr);
                        ls.result = dr::fmadd(c, mis_bsdf, ls.result);
                    }

                    Bool active_next = (ls.depth + 1 < m_max_depth) && si.is_valid();
                    if (dr::none_or<false>(active_next)) {
                        ls.active = active_next;
                        return;
                    }
                    BSDFPtr bsdf = si.bsdf(ls.ray);

                    auto [ds, em_weight, wo, active_em] = sample_emitter(scene, si, ls.sampler, bsdf, active_next);
                    Float sample_1 = ls.sampler->next_1d();
                    Point2f sample_2 = ls.sampler->next_2d();
                    auto [bsdf_val, bsdf_pdf, bs, bsdf_weight] =
                        bsdf->eval_pdf_sample(bsdf_ctx, si, wo, sample_1, sample_2);

                    // the matrix throughput, diag(t)·O on first entering it
                    Rows<K> R = dr::select(ls.reduced, ls.R, m_reduced.template output_rows<K>(ls.t));

                    // A fluorescent vertex's operator A = Σ w_i·M_i (+ its elastic RGB albedo as
                    // band albedos when A lacks it); f·cos = A·cos θo/π (Lambertian), or a
                    // direction-dependent lobe's R·A(ωo)·cos θo per direction (only in scenes that
                    // hold one), its elastic part being the BSDF's own value. Towards the emitter
                    // sample only R·A(ωo)·c (3 values) leaves the call.
                    const bool any_em = dr::any_or<true>(active_em);
                    Coeffs<K> c = dr::zeros<Coeffs<K>>(); // the emitter sample's coefficients
                    if (any_em)
                        c = m_reduced.template emitter_coefficients<K>(ds.emitter, em_weight, active_em);
                    Float u_pick = m_varying ? ls.sampler->next_1d(active_next) : Float(0.f);
                    auto [is_fl, native_elastic, v_fl, R_fl] = m_reduced.template vertex<K, false>(
                        bsdf, si, R, c, wo, bs.wo, bs.pdf, m_directional, u_pick, active_next);
                    if (any_em) {
                        Float mis_em = dr::select(ds.delta, 1.f, mis_weight(ds.pdf, bsdf_pdf));
                        Color3f v_red = Reduced::template apply<K>(
                            Reduced::template scale_columns<K>(R, m_reduced.template band_albedo<K>(bsdf_val)), c);
                        v_fl += dr::select(native_elastic, v_red, 0.f);
                        Color3f v = dr::select(is_fl, v_fl, dr::select(ls.reduced, v_red, ls.t * bsdf_val * em_weight));
                        ls.result[active_em] = dr::fmadd(v, mis_em, ls.result);
                    }

                    m_reduced.template scatter<K>(ls.R, ls.t, ls.reduced, R, R_fl, is_fl, native_elastic, bsdf_weight,
                                                  Mask(true));

                    advance(ls, si, bs);

                    Float r_max = Reduced::template max_abs<K>(ls.R);
                    auto [rr_active, rr_scale] = roulette(ls, dr::select(ls.reduced, r_max, dr::max(ls.t)), active_next);
                    ls.R[rr_active] *= rr_scale;
                    ls.t[rr_active] *= rr_scale;
                    ls.pi = scene->ray_intersect_preliminary(ls.ray, false, false, 0, 0, ls.active);
                });
            // Out-of-gamut colours are clipped per sample, as in the scalar variant.
            return { dr::select(ls.valid_ray, dr::maximum(ls.result, 0.f), 0.f), ls.valid_ray };
        }
    }

    double m_lambda_min = 300.0;
    Reduced m_reduced;   ///< RGB variants: the reduced transport
    size_t m_bsdfs = 0; ///< fluorescent BSDFs this render
    double m_range_lo = 0.0, m_range_hi = 0.0;
    const Scene *m_media_warned = nullptr; ///< the scene last warned of media
    bool m_directional = false; ///< some fluorescent BSDF has a direction-dependent lobe
    bool m_varying = false;     ///< ... that varies over the surface (RGB: a model picked per vertex)
};

static const bool fluo_path_jit_registered =
    (fluo_detail::register_jit_plugin<FluoPathJit>("fluo_path", ObjectType::Integrator), true);

NAMESPACE_END(mitsuba)
