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
    static constexpr size_t KMax = 7;

    FluoPathJit(const Properties &props) : Base(props) {
        m_lambda_min = fluo_detail::lambda_min_of(Plugin, props);
        std::string basis(props.get<std::string_view>("basis", "x7")), method(props.get<std::string_view>("method", "ours"));
        m_transport = fluo_detail::rust_call(Plugin, [&] { return fluo::transport_new(basis, method); });
        m_k = fluo::transport_size(**m_transport);
        if (m_k != 3 && m_k != 4 && m_k != KMax)
            Throw("%s: basis \"%s\" has %zu bands; the transport is compiled for 3, 4 and %zu", Plugin, basis, m_k,
                  KMax);
        m_output.resize(3 * m_k);
        m_from_rgb.resize(3 * m_k);
        m_white.resize(m_k);
        fluo::transport_output(**m_transport, rust::Slice<double>(m_output.data(), m_output.size()));
        fluo::transport_from_rgb(**m_transport, rust::Slice<double>(m_from_rgb.data(), m_from_rgb.size()));
        fluo::transport_white(**m_transport, rust::Slice<double>(m_white.data(), m_white.size()));
    }

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
            if (!m_entries.empty()) {
                if (m_k == 3)
                    return sample_reduced<3>(scene, sampler, ray, active);
                if (m_k == 4)
                    return sample_reduced<4>(scene, sampler, ray, active);
                return sample_reduced<KMax>(scene, sampler, ray, active);
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
            << "  basis = " << fluo::transport_name(**m_transport) << " (K = " << m_k << ")," << std::endl
            << "  fluorescent_bsdfs = " << m_entries.size() << "," << std::endl
            << "  excitation_range = [" << m_range_lo << ", " << m_range_hi << "]," << std::endl
            << "  variant = vectorised" << std::endl
            << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(FluoPathJit)

private:
    /// A fluorescent BSDF and, in RGB variants, its reduced operator Σ w_i·M_i (f = M/π).
    struct Entry {
        const BSDF *bsdf;
        const Bispectral *bispectral;
        bool full = false; ///< the operator includes the elastic part
        std::array<std::vector<double>, Bispectral::MaxTerms> m;
        /// A direction-dependent lobe (Bispectral::jit_reduced_nodes): the terms' weights at
        /// the cosine nodes ([n_nodes][MaxTerms]; the terms' matrices are `m`).
        DynamicBuffer<Float> nodes;
        uint32_t n_nodes = 0;
    };

    /// A fluo_illuminant emitter's basis coefficients (RGB variants).
    struct Source {
        std::vector<double> coeffs;
        double luminance;
        const fluo::Illuminant *illuminant;
    };

    /// Once per render: the fluorescent BSDFs (refusing wrappers, which the vectorised
    /// loop cannot see through), the emitters' spectral range and, in RGB variants,
    /// reduced matrices and the emitters' basis coefficients.
    void prepare(Scene *scene) {
        fluo_detail::warn_if_media(Plugin, scene, m_media_warned);
        m_entries.clear();
        m_sources.clear();
        bool directional = false;
        fluo::Range lights = fluo_detail::emitters_range(scene);
        double lo = std::max(lights.lo, m_lambda_min), hi = lights.hi;
        for (const auto &emitter : scene->emitters()) {
            fluo_detail::Collector ce;
            ce.visit(const_cast<Emitter *>(emitter.get()));
            for (Object *o : ce.objects)
                if (auto *src = dynamic_cast<SpectralSource *>(o); src && is_rgb_v<Spectrum> &&
                                                                    !m_sources.count(emitter.get())) {
                    Source s{ std::vector<double>(m_k), src->rgb_luminance(), &src->illuminant() };
                    fluo::illuminant_coefficients(src->illuminant(), **m_transport,
                                                  rust::Slice<double>(s.coeffs.data(), m_k));
                    m_sources.emplace(emitter.get(), s);
                }
        }
        for (Bispectral *b : fluo_detail::jit_fluorescent_bsdfs<Bispectral>(Plugin, scene)) {
            Entry e{ dynamic_cast<const BSDF *>(b), b };
            hi = std::max(hi, b->jit_emission_range().hi); // re-emitted light can excite further shifts
            directional |= !b->jit_lambertian();
            if constexpr (is_rgb_v<Spectrum>) {
                for (auto &m : e.m)
                    m.assign(m_k * m_k, 0.0);
                e.full = fluo_detail::rust_call(Plugin, [&] { return b->jit_reduced_matrices(**m_transport, e.m); });
                std::vector<double> nodes;
                if (!b->jit_lambertian())
                    e.n_nodes = (uint32_t) fluo_detail::rust_call(
                        Plugin, [&] { return b->jit_reduced_nodes(**m_transport, e.m, nodes); });
                if (e.n_nodes > 0) {
                    std::vector<float> f(nodes.begin(), nodes.end());
                    e.nodes = dr::load<DynamicBuffer<Float>>(f.data(), f.size());
                }
            }
            m_entries.push_back(std::move(e));
        }
        if (is_rgb_v<Spectrum> && !m_entries.empty() && m_uv_warned != scene) {
            for (const auto &[emitter, src] : m_sources)
                if (fluo::illuminant_is_mostly_uv(*src.illuminant)) {
                    fluo_detail::warn_uv_emitter(Plugin, "llvm_ad_rgb", emitter);
                    m_uv_warned = scene;
                    break;
                }
        }
        m_range_lo = lo;
        m_range_hi = hi;
        if (scene->emitters().empty())
            m_entries.clear();
        m_directional = directional && !m_entries.empty();
    }

    const Entry *find(const BSDF *b) const {
        for (const Entry &e : m_entries)
            if (e.bsdf == b)
                return &e;
        return nullptr;
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
        const bool fluorescent = is_spectral_v<Spectrum> && !m_entries.empty(), directional = m_directional;
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

    template <size_t K> using Coeffs = dr::Array<Float, K>;
    template <size_t K> using Rows = dr::Array<Float, 3 * K>;

    /// Per-band albedo a_k = (F·v)_k / (F·1)_k of an RGB value (a native BSDF on the K
    /// coefficients; fluo_transport_reduced.h's band_albedo).
    template <size_t K> Coeffs<K> band_albedo(const Color3f &v) const {
        Coeffs<K> d;
        Float mean = (v[0] + v[1] + v[2]) * (1.f / 3.f);
        for (size_t k = 0; k < K; ++k) {
            double w = m_white[k];
            if (std::abs(w) > 1e-12)
                d[k] = ((float) m_from_rgb[3 * k] * v[0] + (float) m_from_rgb[3 * k + 1] * v[1] +
                        (float) m_from_rgb[3 * k + 2] * v[2]) * (float) (1.0 / w);
            else
                d[k] = mean;
        }
        return d;
    }

    /// Basis coefficients of an emitter's radiance `le` (RGB): a fluo_illuminant's own
    /// coefficients rescaled to the radiance's luminance, else F·le.
    template <size_t K> Coeffs<K> emitter_coefficients(const EmitterPtr &emitter, const Color3f &le,
                                                        const Mask &active) const {
        Coeffs<K> plain;
        for (size_t k = 0; k < K; ++k)
            plain[k] = (float) m_from_rgb[3 * k] * le[0] + (float) m_from_rgb[3 * k + 1] * le[1] +
                       (float) m_from_rgb[3 * k + 2] * le[2];
        // Emitters are compared by pointer (a handful per scene), without a virtual call.
        Coeffs<K> c = plain;
        Float y = 0.212671f * le[0] + 0.715160f * le[1] + 0.072169f * le[2];
        for (const auto &[e, src] : m_sources) {
            Mask is_src = active && emitter == EmitterPtr(e);
            if (dr::none_or<false>(is_src))
                continue;
            Float s = src.luminance > 0.0 ? y * (float) (1.0 / src.luminance) : Float(0.f);
            for (size_t k = 0; k < K; ++k)
                c[k] = dr::select(is_src, s * (float) src.coeffs[k], c[k]);
        }
        return c;
    }

    /// R·c (3×K times K).
    template <size_t K> static Color3f apply(const Rows<K> &R, const Coeffs<K> &c) {
        Color3f out;
        for (size_t r = 0; r < 3; ++r) {
            Float acc = R[r * K] * c[0];
            for (size_t k = 1; k < K; ++k)
                acc = dr::fmadd(R[r * K + k], c[k], acc);
            out[r] = acc;
        }
        return out;
    }
    /// R·diag(d).
    template <size_t K> static Rows<K> scale_columns(Rows<K> R, const Coeffs<K> &d) {
        for (size_t r = 0; r < 3; ++r)
            for (size_t j = 0; j < K; ++j)
                R[r * K + j] *= d[j];
        return R;
    }

    /// R·A for a Lambertian fluorescent vertex, A = Σ w_t·M_t (+ the elastic band albedos
    /// when A lacks them).
    template <size_t K>
    Rows<K> lambertian_product(const Entry &e, const SurfaceInteraction3f &si, const Rows<K> &R, const Mask &on) const {
        return operator_product<K>(e, si, R, e.bispectral->jit_reduced_weights(), !e.full, on);
    }

    /// R·A with A = Σ w_t·M_t (the entry's M_t) plus, if `elastic`, the elastic band albedos
    /// on the diagonal, formed one column of A at a time (the M_t are the material's
    /// constants): K·K values of A never live at once, which at K = 7 spilled registers (a
    /// third of the render time).
    template <size_t K>
    Rows<K> operator_product(const Entry &e, const SurfaceInteraction3f &si, const Rows<K> &R,
                             const std::array<Float, Bispectral::MaxTerms> &w, bool elastic, const Mask &on) const {
        Rows<K> ra;
        Coeffs<K> d = dr::zeros<Coeffs<K>>();
        if (elastic)
            d = band_albedo<K>(e.bispectral->jit_elastic_albedo(si, on));
        for (size_t j = 0; j < K; ++j) {
            Coeffs<K> col = dr::zeros<Coeffs<K>>(); // A[:, j]
            for (size_t k = 0; k < K; ++k) {
                for (size_t t = 0; t < Bispectral::MaxTerms; ++t)
                    if (e.m[t][k * K + j] != 0.0)
                        col[k] = dr::fmadd(w[t], (float) e.m[t][k * K + j], col[k]);
                if (elastic && k == j)
                    col[k] += d[k];
            }
            for (size_t r = 0; r < 3; ++r) {
                Float acc = R[r * K] * col[0];
                for (size_t k = 1; k < K; ++k)
                    acc = dr::fmadd(R[r * K + k], col[k], acc);
                ra[r * K + j] = acc;
            }
        }
        return ra;
    }

    /// For a direction-dependent lobe, R·A(ωo)·cos θo·c towards wa (the emitter sample, with
    /// its coefficients c) and R·A(ωo)·cos θo towards wb: lobe·w_0·R·Σ_t s_t(cos θ)·M_t, the
    /// s_t linear between the entry's nodes (Bispectral::jit_reduced_nodes, jit_lobe). Each
    /// R·M_t column serves both directions.
    template <size_t K>
    std::pair<Color3f, Rows<K>> directional_products(const Entry &e, const SurfaceInteraction3f &si, const Rows<K> &R,
                                                     const Coeffs<K> &c, const Vector3f &wa, const Vector3f &wb,
                                                     const Mask &on) const {
        constexpr uint32_t T = (uint32_t) Bispectral::MaxTerms;
        using Weights = std::array<Float, Bispectral::MaxTerms>;
        auto weights = [&](const Vector3f &wo) {
            auto [lobe, cos_h] = e.bispectral->jit_lobe(si, wo, on);
            Float scale = lobe * e.bispectral->jit_reduced_weights()[0];
            Float x = dr::clip(cos_h, 0.f, 1.f) * (float) (e.n_nodes - 1);
            UInt32 j = dr::minimum(UInt32(dr::floor(x)), e.n_nodes - 2);
            Float f = x - Float(j);
            Mask live = on && lobe != 0.f;
            Weights w;
            for (uint32_t t = 0; t < T; ++t)
                w[t] = dr::lerp(dr::gather<Float>(e.nodes, j * T + t, live),
                                dr::gather<Float>(e.nodes, (j + 1) * T + t, live), f) * scale;
            return w;
        };
        Weights w_a = weights(wa), w_b = weights(wb);
        Color3f out_a = dr::zeros<Color3f>();
        Rows<K> out_b = dr::zeros<Rows<K>>();
        for (size_t t = 0; t < Bispectral::MaxTerms; ++t)
            for (size_t j = 0; j < K; ++j) {
                Float wc = w_a[t] * c[j];
                for (size_t r = 0; r < 3; ++r) {
                    Float acc = 0.f; // (R·M_t)[r, j]
                    bool any = false;
                    for (size_t k = 0; k < K; ++k)
                        if (double m = e.m[t][k * K + j]; m != 0.0) {
                            acc = any ? dr::fmadd(R[r * K + k], (float) m, acc) : R[r * K + k] * (float) m;
                            any = true;
                        }
                    if (!any)
                        continue;
                    out_a[r] = dr::fmadd(wc, acc, out_a[r]);
                    out_b[r * K + j] = dr::fmadd(w_b[t], acc, out_b[r * K + j]);
                }
            }
        return { out_a, out_b };
    }

    template <size_t K>
    std::pair<Spectrum, Bool> sample_reduced(const Scene *scene, Sampler *sampler, const RayDifferential3f &ray_,
                                             Bool active) const {
        if constexpr (!is_rgb_v<Spectrum>) {
            return { 0.f, false };
        } else {
            Rows<K> O; // R = diag(t)·O at the first fluorescent vertex
            for (size_t i = 0; i < 3 * K; ++i)
                O[i] = (float) m_output[i];
            LoopStateR<K> ls = { Ray3f(ray_), dr::zeros<PreliminaryIntersection3f>(), Color3f(1.f),
                                 dr::zeros<Rows<K>>(), Mask(false), Color3f(0.f), Float(1.f), UInt32(0),
                                 Mask(!m_hide_emitters && scene->environment() != nullptr), dr::zeros<Interaction3f>(),
                                 Float(1.f), Bool(true), active, sampler };
            ls.pi = camera_intersection(scene, ls.ray, ls.active);

            dr::tie(ls) = dr::while_loop(
                dr::make_tuple(ls), [](const LoopStateR<K> &ls) { return ls.active; },
                [this, scene, O](LoopStateR<K> &ls) {
                    BSDFContext bsdf_ctx;
                    SurfaceInteraction3f si = ls.pi.compute_surface_interaction(ls.ray, +RayFlags::All);

                    if (dr::any_or<true>(si.emitter(scene) != nullptr)) {
                        auto [emitter, le, mis_bsdf] = hit_emission(scene, si, ls);
                        Color3f c = dr::select(
                            ls.reduced, apply<K>(ls.R, emitter_coefficients<K>(emitter, le, emitter != nullptr)),
                            ls.t * le);
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

                    Rows<K> R; // the matrix throughput, diag(t)·O on first entering it
                    for (size_t r = 0; r < 3; ++r)
                        for (size_t k = 0; k < K; ++k)
                            R[r * K + k] = dr::select(ls.reduced, ls.R[r * K + k], O[r * K + k] * ls.t[r]);

                    // A fluorescent vertex's operator A = Σ w_i·M_i (+ its elastic RGB albedo as
                    // band albedos when A lacks it); f·cos = A·cos θo/π (Lambertian). R·A is
                    // formed in the call (lambertian_product). A direction-dependent lobe
                    // (only in scenes that hold one: `directional`) gives R·A(ωo)·cos θo per
                    // direction instead, its elastic part being the BSDF's own value.
                    Mask is_fl, native_elastic = false;
                    const bool any_em = dr::any_or<true>(active_em);
                    Coeffs<K> c = dr::zeros<Coeffs<K>>(); // the emitter sample's coefficients
                    if (any_em)
                        c = emitter_coefficients<K>(ds.emitter, em_weight, active_em);
                    Rows<K> RA_bs;
                    Color3f v_fl; // R·A(ωo)·c·cos θo towards the emitter sample
                    Float bs_factor;
                    if (!m_directional) {
                        auto [f, RA] = fluo_detail::dispatch_any(
                            bsdf,
                            [this](const BSDF *b, const SurfaceInteraction3f &si_, const Rows<K> &R_, const Mask &on) {
                                const Entry *e = find(b);
                                if (!e)
                                    return std::make_pair(Mask(false), dr::zeros<Rows<K>>());
                                return std::make_pair(Mask(true), lambertian_product<K>(*e, si_, R_, on));
                            },
                            si, R, active_next);
                        is_fl = f;
                        RA_bs = RA;
                        if (any_em)
                            v_fl = apply<K>(RA, c) * Bispectral::lambert(si, wo);
                        bs_factor = dr::select(bs.pdf > 0.f, Bispectral::lambert(si, bs.wo) / bs.pdf, 0.f);
                    } else {
                        // towards the emitter only R·A(ωo)·c is needed: 3 values leave the call, not 3K
                        auto [f, native, va, ra_bs] = fluo_detail::dispatch_any(
                            bsdf,
                            [this](const BSDF *b, const SurfaceInteraction3f &si_, const Rows<K> &R_, const Coeffs<K> &c_,
                                   const Vector3f &wa, const Vector3f &wb, const Mask &on) {
                                const Entry *e = find(b);
                                if (!e)
                                    return std::make_tuple(Mask(false), Mask(false), dr::zeros<Color3f>(),
                                                           dr::zeros<Rows<K>>());
                                if (e->n_nodes == 0) {
                                    Rows<K> ra = lambertian_product<K>(*e, si_, R_, on);
                                    return std::make_tuple(Mask(true), Mask(false),
                                                           apply<K>(ra, c_) * Bispectral::lambert(si_, wa),
                                                           ra * Bispectral::lambert(si_, wb));
                                }
                                auto [va_, rb] = directional_products<K>(*e, si_, R_, c_, wa, wb, on);
                                return std::make_tuple(Mask(true), Mask(true), va_, rb);
                            },
                            si, R, c, wo, bs.wo, active_next);
                        is_fl = f;
                        native_elastic = native;
                        v_fl = va;
                        RA_bs = ra_bs;
                        bs_factor = dr::select(bs.pdf > 0.f, dr::rcp(bs.pdf), 0.f);
                    }
                    is_fl &= active_next;
                    native_elastic &= is_fl;
                    Mask matrix = ls.reduced || is_fl;
                    if (any_em) {
                        Float mis_em = dr::select(ds.delta, 1.f, mis_weight(ds.pdf, bsdf_pdf));
                        Color3f v_red = apply<K>(scale_columns<K>(R, band_albedo<K>(bsdf_val)), c);
                        if (m_directional)
                            v_fl += dr::select(native_elastic, v_red, 0.f);
                        Color3f v = dr::select(is_fl, v_fl, dr::select(ls.reduced, v_red, ls.t * bsdf_val * em_weight));
                        ls.result[active_em] = dr::fmadd(v, mis_em, ls.result);
                    }

                    Rows<K> R_red = scale_columns<K>(R, band_albedo<K>(bsdf_weight));
                    Rows<K> R_fl = RA_bs * bs_factor;
                    if (m_directional)
                        R_fl += dr::select(native_elastic, R_red, 0.f);
                    ls.R = dr::select(is_fl, R_fl, dr::select(ls.reduced, R_red, ls.R));
                    ls.t = dr::select(matrix, ls.t, ls.t * bsdf_weight);
                    ls.reduced = matrix;

                    advance(ls, si, bs);

                    Float r_max = dr::abs(ls.R[0]);
                    for (size_t i = 1; i < 3 * K; ++i)
                        r_max = dr::maximum(r_max, dr::abs(ls.R[i]));
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
    std::optional<rust::Box<fluo::TransportBasis>> m_transport;
    size_t m_k = 3;
    std::vector<double> m_output, m_from_rgb, m_white;
    std::vector<Entry> m_entries;
    std::unordered_map<const Emitter *, Source> m_sources;
    double m_range_lo = 0.0, m_range_hi = 0.0;
    const Scene *m_uv_warned = nullptr;    ///< the scene last warned of a UV emitter
    const Scene *m_media_warned = nullptr; ///< the scene last warned of media
    bool m_directional = false; ///< some fluorescent BSDF has a direction-dependent lobe
};

static const bool fluo_path_jit_registered =
    (fluo_detail::register_jit_plugin<FluoPathJit>("fluo_path", ObjectType::Integrator), true);

NAMESPACE_END(mitsuba)
