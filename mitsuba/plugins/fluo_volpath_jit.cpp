// fluo_volpath in the vectorised variants (llvm_ad_spectral, llvm_ad_rgb; cuda_ad_* the same
// code): Mitsuba's volpath loop (dr::while_loop, one kernel) with the same fluorescence as
// the scalar fluo_volpath in spectral variants: fluorescent media (fluo_qd_medium,
// fluo_dye_medium through fluo_medium_jit.h) re-emit at real collisions, fluorescent
// BSDFs shift at surfaces as in fluo_path. fluo_volpath.cpp documents the estimators and is
// the reference the tests hold this one against. Without fluorescence the render is
// Mitsuba's own volpath (the integrator hands the render to one), in both variants; with
// fluorescence in an RGB variant it raises an error (the reduced transport through media is
// scalar_rgb's only).
#include <mitsuba/core/properties.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/emitter.h>
#include <mitsuba/render/integrator.h>
#include <mitsuba/render/medium.h>
#include <mitsuba/render/phase.h>
#include <mitsuba/render/records.h>
#include <mitsuba/render/scene.h>
#include <mitsuba/render/sensor.h>

#include <sstream>
#include <string>
#include <vector>

#include "fluo_common.h"
#include "fluo_jit.h"
#include "fluo_medium_jit.h"
#include "fluo_path_loop.h"
#include "fluo_path_scene.h"

NAMESPACE_BEGIN(mitsuba)

template <typename Float, typename Spectrum>
class FluoVolpathJit final : public MonteCarloIntegrator<Float, Spectrum> {
public:
    MI_IMPORT_BASE(MonteCarloIntegrator, m_max_depth, m_rr_depth, m_hide_emitters)
    MI_IMPORT_TYPES(Scene, Sensor, Sampler, Medium, MediumPtr, Emitter, EmitterPtr, BSDF, BSDFPtr, Shape,
                    PhaseFunctionContext, PhaseFunction, PhaseFunctionPtr)
    using Bispectral = fluo_detail::JitBispectral<Float, Spectrum>;
    using BMedium = fluo_detail::JitBispectralMedium<Float, Spectrum>;
    using WMask = dr::mask_t<UnpolarizedSpectrum>;

    static constexpr const char *Plugin = "fluo_volpath";
    static constexpr float InvFourPi = fluo_detail::InvFourPi;

    FluoVolpathJit(const Properties &props) : Base(props) {
        m_lambda_min = fluo_detail::lambda_min_of(Plugin, props);
        // basis, method and closed_form_shadows are scalar_rgb's; validated here as there.
        std::string basis = fluo_detail::get_string(props, "basis", "x7"),
                    method = fluo_detail::get_string(props, "method", "ours");
        fluo_detail::rust_call(Plugin, [&] { return fluo::transport_new(basis, method); });
        (void) props.get<bool>("closed_form_shadows", true);
        Properties vp("volpath");
        vp.set("max_depth", (int64_t) props.get<int64_t>("max_depth", -1));
        vp.set("rr_depth", (int64_t) props.get<int64_t>("rr_depth", 5));
        vp.set("hide_emitters", props.get<bool>("hide_emitters", false));
        m_volpath = PluginManager::instance()->create_object<Base>(vp);
    }

    using Base::render;
    TensorXf render(Scene *scene, Sensor *sensor, UInt32 seed, uint32_t spp, bool develop,
                    bool evaluate) override {
        prepare(scene);
        if (!m_fluorescent)
            return m_volpath->render(scene, sensor, seed, spp, develop, evaluate);
        return Base::render(scene, sensor, seed, spp, develop, evaluate);
    }

    std::pair<Spectrum, Bool> sample(const Scene *scene, Sampler *sampler, const RayDifferential3f &ray,
                                     const Medium *medium, Float *aovs, Bool active) const override {
        if constexpr (!is_spectral_v<Spectrum>) {
            return m_volpath->sample(scene, sampler, ray, medium, aovs, active);
        } else {
            if (!m_fluorescent)
                return m_volpath->sample(scene, sampler, ray, medium, aovs, active);
            return trace(scene, sampler, ray, medium, active);
        }
    }

    std::string to_string() const override {
        std::ostringstream oss;
        oss << "FluoVolpath[" << std::endl
            << "  max_depth = " << m_max_depth << "," << std::endl
            << "  rr_depth = " << m_rr_depth << "," << std::endl
            << "  lambda_min = " << m_lambda_min << "," << std::endl
            << "  fluorescent_bsdfs = " << m_bsdfs.size() << "," << std::endl
            << "  fluorescent_media = " << m_media.size() << "," << std::endl
            << "  excitation_range = [" << m_range_lo << ", " << m_range_hi << "]," << std::endl
            << "  variant = vectorised" << std::endl
            << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(FluoVolpathJit)

private:
    /// Once per render: the fluorescent media and BSDFs (refusing wrapped BSDFs, which the
    /// vectorised loop cannot see through) and the emitters' spectral range; whether
    /// anything fluoresces. RGB variants: fluorescence raises an error.
    void prepare(Scene *scene) {
        m_media.clear();
        m_bsdfs.clear();
        std::vector<const BMedium *> media = fluo_detail::managed_media<BMedium>(scene);
        fluo::Range lights = fluo_detail::emitters_range(scene);
        double lo = std::max(lights.lo, m_lambda_min), hi = lights.hi;
        bool directional = false;
        for (Bispectral *b : fluo_detail::jit_fluorescent_bsdfs<Bispectral>(Plugin, scene)) {
            m_bsdfs.push_back(b);
            hi = std::max(hi, b->jit_emission_range().hi); // re-emitted light can excite further shifts
            directional |= !b->jit_lambertian();
        }
        for (const BMedium *b : media)
            if (b->jit_fluorescent(0.0, 1e30))
                hi = std::max(hi, b->jit_range().hi);
        m_range_lo = lo;
        m_range_hi = hi;
        if (scene->emitters().empty())
            m_bsdfs.clear();
        else
            for (const BMedium *b : media)
                if (b->jit_fluorescent(lo, hi))
                    m_media.push_back(b);
        m_directional = directional && !m_bsdfs.empty();
        m_fluorescent = !m_media.empty() || !m_bsdfs.empty();
        if (is_rgb_v<Spectrum> && m_fluorescent)
            Throw("%s: the scene fluoresces (%zu fluorescent media, %zu fluorescent materials), and in the "
                  "vectorised RGB variants fluo_volpath renders scenes without fluorescence only (as volpath): "
                  "the reduced transport through media is scalar_rgb's. Render it in llvm_ad_spectral "
                  "(wavelength shifting), scalar_rgb or scalar_spectral; without media, fluo_path renders "
                  "fluorescent materials in llvm_ad_rgb",
                  Plugin, m_media.size(), m_bsdfs.size());
    }

    static Float mis_weight(const Float &a, const Float &b) { return fluo_detail::detached_mis_weight(a, b); }

    /// Where `medium` is one of the scene's fluorescent media (a handful: compared by pointer).
    Mask is_fluorescent_medium(const MediumPtr &medium, const Mask &active) const {
        Mask out = false;
        for (const BMedium *b : m_media)
            out |= active && medium == MediumPtr(dynamic_cast<const Medium *>(b));
        return out;
    }

    /// μa and μf (1/m at density 1) of the fluorescent media at the wavelengths, once per flight.
    std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum> rates(const MediumPtr &medium, const Wavelength &lambda,
                                                              const Mask &active) const {
        const double lo = m_range_lo, hi = m_range_hi;
        return fluo_detail::dispatch_any(
            medium,
            [lo, hi](const Medium *m, const Wavelength &lambda_, const Mask &on) {
                if (auto *f = dynamic_cast<const BMedium *>(m); f && f->jit_fluorescent(lo, hi))
                    return f->jit_rates(lambda_, lo, hi, on);
                return std::make_pair(UnpolarizedSpectrum(0.f), UnpolarizedSpectrum(0.f));
            },
            lambda, active);
    }

    /// A tentative collision: fluorescent media through jit_sample_interaction with the
    /// flight's rates (their majorant covering the source up to `rate`), the others through
    /// Mitsuba's sample_interaction. Returns it, μf there (0 for the others) and where it is
    /// fluorescent.
    std::tuple<MediumInteraction3f, UnpolarizedSpectrum, Mask>
    sample_medium(const MediumPtr &medium, const Ray3f &ray, const Float &u, const Float &rate,
                  const UnpolarizedSpectrum &mu_a, const UnpolarizedSpectrum &mu_f, const Mask &active) const {
        const double lo = m_range_lo, hi = m_range_hi;
        return fluo_detail::dispatch_any(
            medium,
            [lo, hi](const Medium *m, const Ray3f &ray_, const Float &u_, const Float &rate_,
                     const UnpolarizedSpectrum &mu_a_, const UnpolarizedSpectrum &mu_f_, const Mask &on) {
                if (auto *f = dynamic_cast<const BMedium *>(m); f && f->jit_fluorescent(lo, hi)) {
                    auto [mei, mf] = f->jit_sample_interaction(ray_, u_, rate_, mu_a_, mu_f_, on);
                    return std::make_tuple(mei, mf, Mask(true));
                }
                return std::make_tuple(m->sample_interaction(ray_, u_, UInt32(0), on), UnpolarizedSpectrum(0.f),
                                       Mask(false));
            },
            ray, u, rate, mu_a, mu_f, active);
    }

    /// Null and real collision probabilities in a fluorescent medium: spectral tracking
    /// with the fluorescent source's floor on p_real (fluo_volpath.cpp's spectral_tracking
    /// and collision_probabilities, per lane).
    static std::pair<Float, Float> spectral_tracking(const MediumInteraction3f &mei, const Spectrum &throughput,
                                                     const UnpolarizedSpectrum &mu_f, const Float &inv_len) {
        UnpolarizedSpectrum t = dr::abs(unpolarized_spectrum(throughput));
        Float q_null = dr::max(t * mei.sigma_n), q_real = dr::max(t * mei.sigma_t);
        Float kappa = 0.f;
        for (size_t j = 0; j < dr::size_v<UnpolarizedSpectrum>; ++j) {
            Float source = dr::maximum(mei.sigma_s[j], 0.f) + dr::maximum(mu_f[j], 0.f);
            Float rate = dr::select(inv_len > 0.f, dr::minimum(source, inv_len), source);
            kappa = dr::select(t[j] > 0.f, dr::maximum(kappa, rate), kappa);
        }
        Float total = q_null + q_real, majorant = mei.combined_extinction[0];
        Mask ok = total > 0.f && dr::isfinite(total);
        Float p_real = dr::select(ok, q_real / total, 1.f);
        p_real = dr::select(ok && majorant > 0.f && dr::isfinite(majorant),
                            dr::maximum(p_real, dr::minimum(kappa / majorant, .5f)), p_real);
        p_real = dr::clip(p_real, 0.f, 1.f);
        return { 1.f - p_real, p_real };
    }

    struct LoopState {
        Mask active;
        UInt32 depth;
        Ray3f ray;
        Spectrum throughput, result;
        SurfaceInteraction3f si;
        MediumInteraction3f mei;
        MediumPtr medium;
        Float eta;
        Interaction3f last_scatter_event;
        Float last_scatter_direction_pdf;
        Mask needs_intersection, specular_chain, valid_ray;
        Float inv_len; ///< 1/ℓ of the current straight flight (0: no surface ahead)
        /// μa, μf of a fluorescent medium at the flight's wavelengths (density 1)
        UnpolarizedSpectrum mu_a, mu_f;
        Sampler *sampler;
        DRJIT_STRUCT(LoopState, active, depth, ray, throughput, result, si, mei, medium, eta, last_scatter_event,
                     last_scatter_direction_pdf, needs_intersection, specular_chain, valid_ray, inv_len, mu_a, mu_f,
                     sampler)
    };

    /// volpath's loop with fluorescence (spectral variants with fluorescence only).
    std::pair<Spectrum, Bool> trace(const Scene *scene, Sampler *sampler, const RayDifferential3f &ray_,
                                    const Medium *initial_medium, Bool active) const {
        LoopState ls = { active,
                         UInt32(0),
                         Ray3f(ray_),
                         Spectrum(1.f),
                         Spectrum(0.f),
                         dr::zeros<SurfaceInteraction3f>(),
                         dr::zeros<MediumInteraction3f>(),
                         MediumPtr(initial_medium),
                         Float(1.f),
                         dr::zeros<Interaction3f>(),
                         Float(1.f),
                         Mask(true),
                         Mask(active && !m_hide_emitters),
                         Mask(!m_hide_emitters && scene->environment() != nullptr),
                         Float(0.f),
                         UnpolarizedSpectrum(0.f),
                         UnpolarizedSpectrum(0.f),
                         sampler };
        const bool directional = m_directional, surfaces = !m_bsdfs.empty(), media = !m_media.empty();
        const double range_lo = m_range_lo, range_hi = m_range_hi;

        dr::tie(ls) = dr::while_loop(
            dr::make_tuple(ls), [](const LoopState &ls) { return ls.active; },
            [this, scene, directional, surfaces, media, range_lo, range_hi](LoopState &ls) {
                Mask &active = ls.active;
                Spectrum &throughput = ls.throughput;
                Sampler *sampler = ls.sampler;

                // ----------------- Russian roulette, max_depth -----------------
                active &= dr::any(unpolarized_spectrum(throughput) != 0.f);
                Float q = dr::minimum(dr::max(unpolarized_spectrum(throughput)) * dr::square(ls.eta), .95f);
                Mask perform_rr = ls.depth > (uint32_t) m_rr_depth;
                active &= sampler->next_1d(active) < q || !perform_rr;
                dr::masked(throughput, perform_rr) *= dr::rcp(dr::detach(q));
                active &= ls.depth < (uint32_t) m_max_depth;
                if (dr::none_or<false>(active))
                    return;

                // ------------------------ Sampling the RTE ---------------------
                Mask active_medium = active && ls.medium != nullptr;
                Mask active_surface = active && !active_medium;
                Mask act_null = false, act_scatter = false, escaped = false;
                Mask is_spectral = active_medium, not_spectral = false, is_fluo = false;
                Float p_null = 0.f, p_real = 1.f;
                UnpolarizedSpectrum mu_f = 0.f;
                if (dr::any_or<true>(active_medium)) {
                    is_spectral &= ls.medium->has_spectral_extinction();
                    not_spectral = !is_spectral && active_medium;
                    // A new flight in a fluorescent medium: its length to the next surface first
                    // (the source rate of its tentative collisions is at most 1/ℓ).
                    Mask fluo_flight = ls.needs_intersection && is_fluorescent_medium(ls.medium, active_medium);
                    if (dr::any_or<true>(fluo_flight)) {
                        dr::masked(ls.si, fluo_flight) = scene->ray_intersect(ls.ray, fluo_flight);
                        dr::masked(ls.inv_len, fluo_flight) =
                            dr::select(ls.si.is_valid(), dr::rcp(dr::maximum(ls.si.t, 1e-30f)), 0.f);
                        ls.needs_intersection &= !fluo_flight;
                        auto [mu_a, mu_f_] = rates(ls.medium, ls.ray.wavelengths, fluo_flight);
                        dr::masked(ls.mu_a, fluo_flight) = mu_a;
                        dr::masked(ls.mu_f, fluo_flight) = mu_f_;
                    }
                    Float rate = dr::select(ls.inv_len > 0.f, ls.inv_len, dr::Infinity<Float>);
                    auto [mei, mf, fl] = sample_medium(ls.medium, ls.ray, sampler->next_1d(active_medium), rate,
                                                       ls.mu_a, ls.mu_f, active_medium);
                    dr::masked(ls.mei, active_medium) = mei;
                    mu_f = mf;
                    is_fluo = fl && active_medium;
                    dr::masked(ls.ray.maxt, active_medium && ls.medium->is_homogeneous() && ls.mei.is_valid()) =
                        ls.mei.t;
                    Mask intersect = ls.needs_intersection && active_medium;
                    if (dr::any_or<true>(intersect))
                        dr::masked(ls.si, intersect) = scene->ray_intersect(ls.ray, intersect);
                    ls.needs_intersection &= !active_medium;
                    dr::masked(ls.mei.t, active_medium && ls.si.t < ls.mei.t) = dr::Infinity<Float>;
                    if (dr::any_or<true>(is_spectral)) {
                        auto [tr, free_flight_pdf] = ls.medium->transmittance_eval_pdf(ls.mei, ls.si, is_spectral);
                        Float tr_pdf = free_flight_pdf[0];
                        dr::masked(throughput, is_spectral) *= dr::select(tr_pdf > 0.f, tr / tr_pdf, 0.f);
                    }
                    escaped = active_medium && !ls.mei.is_valid();
                    active_medium &= ls.mei.is_valid();
                    is_spectral &= active_medium;
                    not_spectral &= active_medium;
                    is_fluo &= active_medium;

                    // Null or real: volpath's rule, spectral tracking in fluorescent media.
                    p_null = dr::mean(ls.mei.sigma_n / ls.mei.combined_extinction);
                    p_real = dr::mean(ls.mei.sigma_t / ls.mei.combined_extinction);
                    if (media && dr::any_or<true>(is_fluo)) {
                        auto [pn, pr] = spectral_tracking(ls.mei, throughput, mu_f, ls.inv_len);
                        p_null = dr::select(is_fluo, pn, p_null);
                        p_real = dr::select(is_fluo, pr, p_real);
                    }
                    Mask null_scatter = sampler->next_1d(active_medium) < p_null;
                    act_null = null_scatter && active_medium;
                    act_scatter = !null_scatter && active_medium;
                    dr::masked(throughput, act_null && is_spectral) *= ls.mei.sigma_n / p_null;
                    dr::masked(ls.depth, act_scatter) += 1;
                    dr::masked(ls.last_scatter_event, act_scatter) = Interaction3f(ls.mei);
                }

                active &= ls.depth < (uint32_t) m_max_depth;
                act_scatter &= active;

                dr::masked(ls.ray.o, act_null) = ls.mei.p;
                dr::masked(ls.si.t, act_null) = ls.si.t - ls.mei.t;

                if (dr::any_or<true>(act_scatter)) {
                    // Elastic scattering, or per wavelength a shift to λi (fluo_volpath.cpp).
                    UnpolarizedSpectrum sigma_s = ls.mei.sigma_s;
                    WMask shifted = false;
                    Mask fl_scatter = act_scatter && is_fluo;
                    if (media && dr::any_or<true>(fl_scatter)) {
                        Wavelength ux, uy;
                        for (size_t j = 0; j < dr::size_v<Wavelength>; ++j) {
                            Point2f u = sampler->next_2d(fl_scatter);
                            ux[j] = u.x();
                            uy[j] = u.y();
                        }
                        auto [li, ok] = fluo_detail::dispatch_any(
                            ls.medium,
                            [range_lo, range_hi](const Medium *m, const MediumInteraction3f &mei_, const Wavelength &u_,
                                                 const Mask &on) {
                                if (auto *f = dynamic_cast<const BMedium *>(m); f && f->jit_fluorescent(range_lo, range_hi))
                                    return f->jit_excitation(mei_, u_, range_lo, range_hi, on);
                                return std::make_pair(mei_.wavelengths, WMask(false));
                            },
                            ls.mei, uy, fl_scatter);
                        for (size_t j = 0; j < dr::size_v<UnpolarizedSpectrum>; ++j) {
                            Float ss = dr::maximum(ls.mei.sigma_s[j], 0.f), sf = dr::maximum(mu_f[j], 0.f);
                            Float total = ss + sf;
                            Mask valid = total > 0.f && dr::isfinite(total);
                            Mask elastic = ux[j] * total < ss;
                            Mask shift = fl_scatter && valid && !elastic && ok[j];
                            // both events weigh σs + μf (over their probability); 0 where none can go on
                            sigma_s[j] = dr::select(fl_scatter, dr::select(valid && (elastic || shift), total, 0.f),
                                                    sigma_s[j]);
                            shifted[j] = shift;
                        }
                        ls.mei.wavelengths = dr::select(shifted, li, ls.mei.wavelengths);
                    }
                    dr::masked(throughput, act_scatter && is_spectral) *= sigma_s / p_real;
                    dr::masked(throughput, act_scatter && not_spectral) *= ls.mei.sigma_s / ls.mei.sigma_t;
                    // A collision that absorbed every wavelength for good ends the path.
                    Mask dead = fl_scatter && dr::all(unpolarized_spectrum(throughput) == 0.f);
                    active &= !dead;
                    act_scatter &= !dead;

                    PhaseFunctionContext phase_ctx(sampler);
                    PhaseFunctionPtr phase = ls.mei.medium->phase_function();
                    dr::masked(phase, !act_scatter) = nullptr;

                    // ------------------------ Emitter sampling -----------------
                    Mask sample_emitters = ls.mei.medium->use_emitter_sampling();
                    ls.valid_ray |= act_scatter;
                    ls.specular_chain &= !act_scatter;
                    ls.specular_chain |= act_scatter && !sample_emitters;
                    Mask active_e = act_scatter && sample_emitters;
                    if (dr::any_or<true>(active_e)) {
                        auto [emitted, ds] = sample_emitter(ls.mei, scene, sampler, ls.medium, active_e);
                        auto [phase_val, phase_pdf] = phase->eval_pdf(phase_ctx, ls.mei, ds.d, active_e);
                        // shifted wavelengths re-emit isotropically
                        phase_val = dr::select(shifted, InvFourPi, phase_val);
                        Float mis = mis_weight(ds.pdf, dr::select(ds.delta, 0.f, phase_pdf));
                        dr::masked(ls.result, active_e) += throughput * phase_val * emitted * mis;
                    }

                    // ---------------------- Phase function sampling ------------
                    Float phase_1 = sampler->next_1d(act_scatter);
                    Point2f phase_2 = sampler->next_2d(act_scatter);
                    auto [wo, phase_weight, phase_pdf] = phase->sample(phase_ctx, ls.mei, phase_1, phase_2, act_scatter);
                    act_scatter &= phase_pdf > 0.f;
                    phase_weight = dr::select(shifted, InvFourPi / phase_pdf, phase_weight);
                    dr::masked(ls.ray, act_scatter) = ls.mei.spawn_ray(wo); // carries λi where shifted
                    ls.needs_intersection |= act_scatter;
                    dr::masked(ls.last_scatter_direction_pdf, act_scatter) = phase_pdf;
                    dr::masked(throughput, act_scatter) *= phase_weight;
                }

                // ----------------------- Surface interactions ------------------
                active_surface |= escaped;
                Mask intersect = active_surface && ls.needs_intersection;
                if (dr::any_or<true>(intersect))
                    dr::masked(ls.si, intersect) = scene->ray_intersect(ls.ray, intersect);
                ls.needs_intersection &= !intersect;

                if (dr::any_or<true>(active_surface)) {
                    // Hidden area emitters on the camera ray are skipped, as the scalar variant does.
                    if (m_hide_emitters) {
                        Mask skip = intersect && ls.depth == 0u && ls.si.is_valid() &&
                                    ls.si.shape->emitter() != nullptr;
                        if (dr::any_or<true>(skip)) {
                            Ray3f skip_ray = ls.si.spawn_ray(ls.ray.d);
                            PreliminaryIntersection3f pi = Base::skip_area_emitters(scene, skip_ray, true, skip);
                            dr::masked(ls.si, skip) = pi.compute_surface_interaction(skip_ray, +RayFlags::All, skip);
                        }
                    }
                    Mask count_direct = ls.depth == 0u || ls.specular_chain;
                    EmitterPtr emitter = ls.si.emitter(scene);
                    Mask active_e = active_surface && emitter != nullptr && !(ls.depth == 0u && m_hide_emitters);
                    if (dr::any_or<true>(active_e)) {
                        Float emitter_pdf = 1.f;
                        Mask mis_e = active_e && !count_direct;
                        if (dr::any_or<true>(mis_e)) {
                            DirectionSample3f ds(scene, ls.si, ls.last_scatter_event);
                            dr::masked(emitter_pdf, mis_e) = scene->pdf_emitter_direction(ls.last_scatter_event, ds, mis_e);
                        }
                        Spectrum emitted = emitter->eval(ls.si, active_e);
                        Spectrum contrib = dr::select(
                            count_direct, throughput * emitted,
                            throughput * mis_weight(ls.last_scatter_direction_pdf, emitter_pdf) * emitted);
                        dr::masked(ls.result, active_e) += contrib;
                    }
                }
                active_surface &= ls.si.is_valid();
                if (dr::any_or<true>(active_surface)) {
                    BSDFContext ctx;
                    SurfaceInteraction3f &si = ls.si;
                    BSDFPtr bsdf = si.bsdf(ls.ray);
                    fluo_detail::JitSurfaceShift<Float, Spectrum> shift;
                    if (surfaces)
                        shift.choose(bsdf, si, sampler, active_surface, range_lo, range_hi);

                    // ------------------------ Emitter sampling -----------------
                    Mask active_e = active_surface && has_flag(bsdf->flags(), BSDFFlags::Smooth) &&
                                    ls.depth + 1 < (uint32_t) m_max_depth;
                    Spectrum emitted = 0.f;
                    DirectionSample3f ds = dr::zeros<DirectionSample3f>();
                    if (dr::any_or<true>(active_e))
                        std::tie(emitted, ds) = sample_emitter(si, scene, sampler, ls.medium, active_e);
                    Vector3f wo = si.to_local(ds.d);

                    // ---------------- Emitter contribution, BSDF sampling ------
                    Float sample_1 = sampler->next_1d(active_surface);
                    Point2f sample_2 = sampler->next_2d(active_surface);
                    auto [bsdf_val, bsdf_pdf, bs, bsdf_weight] =
                        bsdf->eval_pdf_sample(ctx, si, wo, sample_1, sample_2, active_surface);
                    if (surfaces)
                        shift.apply(bsdf, si, directional, wo, bs, active_surface, bsdf_val, bsdf_weight);
                    if (dr::any_or<true>(active_e)) {
                        Float mis = mis_weight(ds.pdf, dr::select(ds.delta, 0.f, bsdf_pdf));
                        dr::masked(ls.result, active_e) += throughput * bsdf_val * mis * emitted;
                    }

                    dr::masked(throughput, active_surface) *= bsdf_weight;
                    dr::masked(ls.eta, active_surface) *= bs.eta;
                    dr::masked(ls.ray, active_surface) = si.spawn_ray(si.to_world(bs.wo)); // carries λi
                    ls.needs_intersection |= active_surface;

                    Mask non_null = active_surface && !has_flag(bs.sampled_type, BSDFFlags::Null);
                    dr::masked(ls.depth, non_null) += 1;
                    dr::masked(ls.last_scatter_event, non_null) = Interaction3f(si);
                    dr::masked(ls.last_scatter_direction_pdf, non_null) = bs.pdf;
                    ls.valid_ray |= non_null;
                    ls.specular_chain |= non_null && has_flag(bs.sampled_type, BSDFFlags::Delta);
                    ls.specular_chain &= !(active_surface && has_flag(bs.sampled_type, BSDFFlags::Smooth));
                    Mask transition = active_surface && si.is_medium_transition();
                    dr::masked(ls.medium, transition) = si.target_medium(ls.ray.d);
                }
                active &= active_surface || active_medium;
            });
        return { ls.result, ls.valid_ray };
    }

    struct ShadowState {
        Mask active;
        Ray3f ray;
        Float total_dist;
        Mask needs_intersection;
        MediumPtr medium;
        SurfaceInteraction3f si;
        MediumInteraction3f mei;
        Spectrum transmittance;
        UnpolarizedSpectrum mu_a; ///< μa of a fluorescent medium at the ray's wavelengths (density 1)
        Sampler *sampler;
        DRJIT_STRUCT(ShadowState, active, ray, total_dist, needs_intersection, medium, si, mei, transmittance, mu_a,
                     sampler)
    };

    /// An emitter sample seen from `ref` (at ref.wavelengths) and its transmittance
    /// through media (ratio tracking; fluorescent media with their absorption majorant)
    /// and null interfaces, as volpath's sample_emitter.
    template <typename Interaction>
    std::pair<Spectrum, DirectionSample3f> sample_emitter(const Interaction &ref, const Scene *scene, Sampler *sampler,
                                                          MediumPtr medium, Mask active) const {
        auto [ds, emitter_val] = scene->sample_emitter_direction(ref, sampler->next_2d(active), false, active);
        dr::masked(emitter_val, ds.pdf == 0.f) = 0.f;
        active &= ds.pdf != 0.f;
        if (dr::none_or<false>(active))
            return { emitter_val, ds };

        Ray3f ray = ref.spawn_ray_to(ds.p);
        Float max_dist = ray.maxt;
        if constexpr (std::is_convertible_v<Interaction, SurfaceInteraction3f>)
            dr::masked(medium, ref.is_medium_transition()) = ref.target_medium(ray.d);

        ShadowState ss = { active,
                           ray,
                           Float(0.f),
                           Mask(true),
                           medium,
                           dr::zeros<SurfaceInteraction3f>(),
                           dr::zeros<MediumInteraction3f>(),
                           Spectrum(1.f),
                           UnpolarizedSpectrum(0.f),
                           sampler };
        dr::tie(ss) = dr::while_loop(
            dr::make_tuple(ss), [](const ShadowState &ss) { return dr::detach(ss.active); },
            [this, scene, max_dist, ds](ShadowState &ss) {
                Float remaining = max_dist - ss.total_dist;
                ss.ray.maxt = remaining;
                ss.active &= remaining > 0.f;
                if (dr::none_or<false>(ss.active))
                    return;
                Mask escaped = false;
                Mask active_medium = ss.active && ss.medium != nullptr;
                Mask active_surface = ss.active && !active_medium;
                if (dr::any_or<true>(active_medium)) {
                    // a fluorescent medium's μa, once per segment (the rate is 0: absorption alone)
                    Mask segment = ss.needs_intersection && is_fluorescent_medium(ss.medium, active_medium);
                    if (dr::any_or<true>(segment))
                        dr::masked(ss.mu_a, segment) = rates(ss.medium, ss.ray.wavelengths, segment).first;
                    auto [mei, mu_f, fl] = sample_medium(ss.medium, ss.ray, ss.sampler->next_1d(active_medium),
                                                         Float(0.f), ss.mu_a, UnpolarizedSpectrum(0.f), active_medium);
                    (void) mu_f, (void) fl;
                    dr::masked(ss.mei, active_medium) = mei;
                    dr::masked(ss.ray.maxt, active_medium && ss.medium->is_homogeneous() && ss.mei.is_valid()) =
                        dr::minimum(ss.mei.t, remaining);
                    Mask intersect = ss.needs_intersection && active_medium;
                    if (dr::any_or<true>(intersect))
                        dr::masked(ss.si, intersect) = scene->ray_intersect(ss.ray, intersect);
                    dr::masked(ss.mei.t, active_medium && ss.si.t < ss.mei.t) = dr::Infinity<Float>;
                    ss.needs_intersection &= !active_medium;

                    Mask is_spectral = ss.medium->has_spectral_extinction() && active_medium;
                    Mask not_spectral = !is_spectral && active_medium;
                    if (dr::any_or<true>(is_spectral)) {
                        Float t = dr::minimum(remaining, dr::minimum(ss.mei.t, ss.si.t)) - ss.mei.mint;
                        UnpolarizedSpectrum tr = dr::exp(-t * ss.mei.combined_extinction);
                        UnpolarizedSpectrum pdf = dr::select(ss.si.t < ss.mei.t || ss.mei.t > remaining, tr,
                                                             tr * ss.mei.combined_extinction);
                        Float tr_pdf = pdf[0];
                        dr::masked(ss.transmittance, is_spectral) *= dr::select(tr_pdf > 0.f, tr / tr_pdf, 0.f);
                    }
                    dr::masked(ss.total_dist, active_medium && ss.mei.t > remaining && ss.mei.is_valid()) = ds.dist;
                    dr::masked(ss.mei.t, active_medium && ss.mei.t > remaining) = dr::Infinity<Float>;
                    escaped = active_medium && !ss.mei.is_valid();
                    active_medium &= ss.mei.is_valid();
                    is_spectral &= active_medium;
                    not_spectral &= active_medium;
                    dr::masked(ss.total_dist, active_medium) += ss.mei.t;
                    dr::masked(ss.ray.o, active_medium) = ss.mei.p;
                    dr::masked(ss.si.t, active_medium) = ss.si.t - ss.mei.t;
                    dr::masked(ss.transmittance, is_spectral) *= ss.mei.sigma_n;
                    dr::masked(ss.transmittance, not_spectral) *= ss.mei.sigma_n / ss.mei.combined_extinction;
                }

                Mask intersect = active_surface && ss.needs_intersection;
                if (dr::any_or<true>(intersect))
                    dr::masked(ss.si, intersect) = scene->ray_intersect(ss.ray, intersect);
                ss.needs_intersection &= !intersect;
                active_surface |= escaped;
                dr::masked(ss.total_dist, active_surface) += ss.si.t;

                active_surface &= ss.si.is_valid() && ss.active && !active_medium;
                if (dr::any_or<true>(active_surface)) {
                    BSDFPtr bsdf = ss.si.bsdf(ss.ray);
                    Spectrum v = bsdf->eval_null_transmission(ss.si, active_surface);
                    dr::masked(ss.transmittance, active_surface) *= v;
                }
                dr::masked(ss.ray, active_surface) = ss.si.spawn_ray(ss.ray.d);
                ss.ray.maxt = remaining;
                ss.needs_intersection |= active_surface;
                ss.active &= (active_medium || active_surface) &&
                             dr::any(unpolarized_spectrum(ss.transmittance) != 0.f);
                Mask transition = active_surface && ss.si.is_medium_transition();
                dr::masked(ss.medium, transition) = ss.si.target_medium(ss.ray.d);
            });
        return { emitter_val * ss.transmittance, ds };
    }

    double m_lambda_min = 300.0;
    ref<Base> m_volpath; ///< the render without fluorescence
    std::vector<const BMedium *> m_media;
    std::vector<const Bispectral *> m_bsdfs;
    double m_range_lo = 0.0, m_range_hi = 0.0;
    bool m_fluorescent = false, m_directional = false;
};

static const bool fluo_volpath_jit_registered =
    (fluo_detail::register_jit_plugin<FluoVolpathJit>("fluo_volpath", ObjectType::Integrator), true);

NAMESPACE_END(mitsuba)
