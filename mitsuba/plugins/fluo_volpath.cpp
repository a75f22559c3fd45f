// The fluo_volpath integrator: Mitsuba's volumetric path tracer (volpath) extended with
// fluorescence in participating media and at surfaces. Its documentation is the
// comment below. The loop is a scalar port of Mitsuba 3.8's volpath.cpp; what a path
// carries and what a surface vertex does to it is fluo_path's wavelength-shifting
// transport (include/fluo/fluo_transport_spectral.h), and media are seen through fluo's
// bispectral medium interface (include/fluo/fluo_bispectral_medium.h).
#include <mitsuba/core/properties.h>
#include <mitsuba/core/ray.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/emitter.h>
#include <mitsuba/render/integrator.h>
#include <mitsuba/render/medium.h>
#include <mitsuba/render/phase.h>
#include <mitsuba/render/records.h>
#include <mitsuba/render/sensor.h>
#include <mitsuba/render/shape.h>

#include <algorithm>
#include <array>
#include <sstream>
#include <string>
#include <unordered_map>
#include <vector>

#include "fluo_bispectral.h"
#include "fluo_bispectral_medium.h"
#include "fluo_common.h"
#include "fluo_path_loop.h"
#include "fluo_path_scene.h"
#include "fluo_transport_spectral.h"

NAMESPACE_BEGIN(mitsuba)

/**!

.. _integrator-fluo_volpath:

Wavelength-shifting volumetric path tracer (:monosp:`fluo_volpath`)
-------------------------------------------------------------------

.. pluginparameters::

 * - max_depth
   - |int|
   - Longest path depth; -1 means infinite, 1 only direct emission. (Default: -1)
 * - rr_depth
   - |int|
   - Depth at which Russian roulette starts. (Default: 5)
 * - hide_emitters
   - |bool|
   - Hide directly visible emitters. (Default: false)
 * - lambda_min
   - |float|
   - Shortest excitation wavelength ever shifted to, nm, in [200, 360], as for
     ``fluo_path``. (Default: 300)

Mitsuba's ``volpath`` (delta tracking with null collisions, next-event estimation
through media with ratio-tracked transmittance, MIS between emitter and phase/BSDF
sampling, index-matched ``null`` boundaries, Russian roulette) in ``scalar_spectral``
and ``scalar_rgb``, extended with fluorescence:

* **in media** that implement fluo's bispectral medium interface (``fluo_qd_medium``):
  at an absorption event the medium re-emits isotropically at a longer wavelength;
* **at surfaces**: everything ``fluo_path`` does for fluo's fluorescent BSDFs
  (``fluo_jung``, ``fluo_qd``, ``fluo_matrix``, ``fluo_gmm``, inside ``twosided``,
  ``blendbsdf``, ``mask``), with the same code.

**Without fluorescence it is volpath.** At render start the scene is scanned for
fluorescent BSDFs and media (and the emitters' spectral range R, as ``fluo_path`` does;
re-emission by media extends R to the media's emission range). With none left the
loop draws the same random numbers in the same order and does the same arithmetic as
``volpath``: identical images (tested for homogeneous and grid media, both variants).
A medium with ``quantum_yield`` 0 is a plain absorbing, scattering medium.

**Fluorescent collisions (the estimator).** A camera path carries four hero
wavelengths λo. Delta tracking samples a tentative collision with the medium's majorant
(``fluo_qd_medium``'s is shared by the hero wavelengths) and classifies it as null or
real (σt = σa + σs: all of the absorption, fluorescent or not, attenuates). Native
media keep volpath's rule (the mean of σn/μ̄ over the hero wavelengths); in fluorescent
media the probabilities follow spectral tracking (Kutz et al. 2017): in proportion to
max_j |T_j| σn_j and max_j |T_j| σt_j over the wavelengths' throughputs T, so that a
wavelength in a transparent part of the spectrum is not dragged to zero by one deep in
the absorption band (volpath's rule makes such a medium's transmittance estimate
vanish, with probability ~0.75^n after n null collisions). At a real collision, for
each λo
the radiative transfer equation's source is

    σs(λo) ∫ p(ω, ω') L(λo, ω') dω'  +  ∫_R μa(λi) f(λi → λo) (1/4π) ∫ L(λi, ω') dω' dλi

(elastic in-scattering plus isotropic re-emission of light absorbed at λi ∈ R; f is the
medium's reradiation per unit absorbed power). With μf(λo) = ∫_R μa f dλi (the
medium's ``shift_coefficients``), each λo independently picks the elastic event with
probability pe = σs/(σs + μf), else a shift, sampling λi ∝ μa(λi) f(λi → λo) (exactly:
the medium inverts its CDF). Both branches then carry the same weight σs + μf in place
of volpath's σs, so the estimator of each λo's source is unbiased, and a wavelength with
σs + μf = 0 stops contributing. The new direction is shared: it is sampled from the
medium's phase function, and the shifted wavelengths weigh it by the isotropic 1/(4π)
instead of the phase value (in next-event estimation and in the sampled direction;
the MIS weights use the sampling pdfs, which do not depend on wavelength). Shifted
wavelengths continue with their excitation wavelength: transmittance, later
collisions, surfaces and emitters all see λi, and the film still receives the camera
wavelengths. Energy: the medium guarantees ∫ f dλo ≤ Q, so re-emitted power never
exceeds the yield times the absorbed power (a closed-furnace test checks it).

**Cost.** Tracking takes about one tentative collision per unit optical depth of the
most opaque hero wavelength (each a call into the medium's Rust tables): optically
thick fluorescent media (τ ≫ 100 over the scene) render slowly; fluorescence itself
costs one excitation sample per shifted wavelength at real collisions.

**Variants.** Fluorescence is transported in ``scalar_spectral``. In ``scalar_rgb`` a
scene with a fluorescent medium or fluorescent BSDF is refused at render start with an
error (reduced RGB transport for media is not implemented; for surfaces without media
use ``fluo_path``), never rendered without its glow; without fluorescence
``scalar_rgb`` renders exactly as ``volpath``.

Mitsuba's ``volpath`` renders fluorescent media as absorbing only (their Q = 0 limit)
and warns once per scene.

.. tabs::
    .. code-tab:: xml

        <integrator type="fluo_volpath">
            <integer name="max_depth" value="16"/>
        </integrator>
*/
template <typename Float, typename Spectrum>
class FluoVolpath final : public MonteCarloIntegrator<Float, Spectrum> {
public:
    MI_IMPORT_BASE(MonteCarloIntegrator, m_max_depth, m_rr_depth, m_hide_emitters)
    MI_IMPORT_TYPES(Scene, Sensor, Sampler, Emitter, EmitterPtr, BSDF, BSDFPtr, Medium, MediumPtr, Shape,
                    PhaseFunctionContext)
    using Spectral = SpectralTransport<Float, Spectrum>;
    using Path = typename Spectral::Path;
    using EmitterSample = fluo_detail::EmitterSample<Float, Spectrum>;
    using BMedium = BispectralMedium<Float, Spectrum>;

    static constexpr const char *Plugin = "fluo_volpath";
    /// Allowed range of `lambda_min`, nm (as fluo_path).
    static constexpr double LambdaMinLo = 200.0, LambdaMinHi = 360.0;
    /// Isotropic re-emission, 1/(4π) per steradian.
    static constexpr float InvFourPi = (float) (0.25 * M_1_PI);

    FluoVolpath(const Properties &props) : Base(props), m_lambda_min(lambda_min_of(props)) {}

    using Base::render;
    TensorXf render(Scene *scene, Sensor *sensor, UInt32 seed, uint32_t spp, bool develop,
                    bool evaluate) override {
        prepare(scene);
        return Base::render(scene, sensor, seed, spp, develop, evaluate);
    }

    std::pair<Spectrum, Bool> sample(const Scene *scene, Sampler *sampler, const RayDifferential3f &ray_,
                                     const Medium *initial_medium, Float * /* aovs */,
                                     Bool active) const override {
        Path path(m_spectral);
        Bool valid_ray = !m_hide_emitters && (scene->environment() != nullptr);
        Ray3f ray = Ray3f(ray_);
        Float eta = 1.f;
        MediumPtr medium = initial_medium;
        MediumInteraction3f mei = dr::zeros<MediumInteraction3f>();
        Bool specular_chain = active && !m_hide_emitters;
        uint32_t depth = 0;

        uint32_t channel = 0;
        if constexpr (is_rgb_v<Spectrum>) {
            uint32_t n = (uint32_t) dr::size_v<Spectrum>;
            channel = (uint32_t) dr::minimum(sampler->next_1d(active) * (float) n, (float) (n - 1));
        }

        SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>();
        Interaction3f last_scatter_event = dr::zeros<Interaction3f>();
        Bool needs_intersection = true;
        Float last_scatter_direction_pdf = 1.f;

        while (active) {
            // ----------------- Russian roulette, max_depth -----------------
            Spectrum &throughput = path.throughput();
            active &= dr::any(unpolarized_spectrum(throughput) != 0.f);
            Float q = dr::minimum(dr::max(unpolarized_spectrum(throughput)) * dr::square(eta), .95f);
            Bool perform_rr = depth > (uint32_t) m_rr_depth;
            active &= sampler->next_1d(active) < q || !perform_rr;
            if (perform_rr)
                throughput *= dr::rcp(q);
            active &= depth < (uint32_t) m_max_depth;
            if (!active)
                break;

            // ------------------------ Sampling the RTE ---------------------
            Bool active_medium = medium != nullptr;
            Bool active_surface = !active_medium;
            Bool act_null_scatter = false, act_medium_scatter = false, escaped_medium = false;
            Bool is_spectral = active_medium, not_spectral = false;
            Float null_scatter_prob = 0.f, real_scatter_prob = 1.f;
            const MediumEntry *fluo_entry = nullptr;
            if (active_medium) {
                is_spectral = medium->has_spectral_extinction();
                not_spectral = !is_spectral;
                mei = medium->sample_interaction(ray, sampler->next_1d(active_medium), channel, active_medium);
                if (medium->is_homogeneous() && mei.is_valid())
                    ray.maxt = mei.t;
                if (needs_intersection)
                    si = scene->ray_intersect(ray, true);
                needs_intersection = false;
                if (si.t < mei.t)
                    mei.t = dr::Infinity<Float>;
                if (is_spectral) {
                    auto [tr, free_flight_pdf] = medium->transmittance_eval_pdf(mei, si, true);
                    Float tr_pdf = free_flight_pdf[channel];
                    throughput *= dr::select(tr_pdf > 0.f, tr / tr_pdf, 0.f);
                }
                escaped_medium = !mei.is_valid();
                active_medium = mei.is_valid();
                is_spectral &= active_medium;
                not_spectral &= active_medium;
                if (active_medium) {
                    // Null or real: volpath's rule (the hero wavelengths' mean null
                    // probability), or spectral tracking in fluorescent media.
                    fluo_entry = find_medium(mei.medium);
                    if (fluo_entry && is_spectral) {
                        std::tie(null_scatter_prob, real_scatter_prob) = spectral_tracking(mei, throughput);
                    } else {
                        null_scatter_prob = dr::mean(mei.sigma_n / mei.combined_extinction);
                        real_scatter_prob = dr::mean(mei.sigma_t / mei.combined_extinction);
                    }
                    Bool null_scatter = sampler->next_1d(active_medium) < null_scatter_prob;
                    act_null_scatter = null_scatter;
                    act_medium_scatter = !null_scatter;
                    if (is_spectral && act_null_scatter)
                        throughput *= mei.sigma_n / null_scatter_prob;
                    if (act_medium_scatter) {
                        depth += 1;
                        last_scatter_event = Interaction3f(mei);
                    }
                }
            }

            active &= depth < (uint32_t) m_max_depth;
            act_medium_scatter &= active;

            if (act_null_scatter) {
                ray.o = mei.p;
                si.t = si.t - mei.t;
            }

            if (act_medium_scatter) {
                // Elastic scattering, or fluorescence per wavelength (see the docs).
                UnpolarizedSpectrum sigma_s = mei.sigma_s;
                MediumShift shift;
                if (fluo_entry)
                    shift = choose_medium_shift(*fluo_entry, mei, sampler, sigma_s);

                if (is_spectral)
                    throughput *= sigma_s / real_scatter_prob;
                if (not_spectral)
                    throughput *= sigma_s / mei.sigma_t;

                PhaseFunctionContext phase_ctx(sampler);
                const auto *phase = mei.medium->phase_function();

                // ------------------------ Emitter sampling -----------------
                Bool sample_emitters = mei.medium->use_emitter_sampling();
                valid_ray = true;
                specular_chain = !sample_emitters;
                if (sample_emitters) {
                    auto [emitted, ds] = sample_emitter(mei, scene, sampler, medium, channel);
                    auto [phase_val, phase_pdf] = phase->eval_pdf(phase_ctx, mei, ds.d, true);
                    shift.apply(phase_val);
                    path.add_radiance(phase_val * emitted *
                                      fluo_detail::mis_weight(ds.pdf, dr::select(ds.delta, 0.f, phase_pdf)));
                }

                // ---------------------- Phase function sampling ------------
                // volpath passes next_1d(), next_2d() as call arguments; the Linux wheel's
                // build evaluates them right to left, so the 2D sample is drawn first (and
                // so here: the same random numbers, test_fluo_volpath.py test01).
                Point2f phase_2 = sampler->next_2d(true);
                Float phase_1 = sampler->next_1d(true);
                auto [wo, phase_weight, phase_pdf] = phase->sample(phase_ctx, mei, phase_1, phase_2, true);
                act_medium_scatter &= phase_pdf > 0.f;
                if (act_medium_scatter) {
                    if (shift.any)
                        shift.apply_weight(phase_weight, phase_pdf);
                    ray = mei.spawn_ray(wo);
                    needs_intersection = true;
                    last_scatter_direction_pdf = phase_pdf;
                    throughput *= phase_weight;
                }
            }

            // ----------------------- Surface interactions ------------------
            active_surface |= escaped_medium;
            Bool intersected = active_surface && needs_intersection;
            if (intersected)
                si = scene->ray_intersect(ray, true);

            if (active_surface) {
                // Hidden area emitters on the camera ray are skipped, as volpath does.
                if (m_hide_emitters && depth == 0u && intersected && si.is_valid() &&
                    si.shape->emitter() != nullptr) {
                    Ray3f skip_ray = si.spawn_ray(ray.d);
                    PreliminaryIntersection3f pi = Base::skip_area_emitters(scene, skip_ray, true, true);
                    si = pi.compute_surface_interaction(skip_ray, +RayFlags::All, true);
                }
                Bool count_direct = (depth == 0u) || specular_chain;
                const Emitter *emitter = si.emitter(scene);
                if (emitter != nullptr && !(depth == 0u && m_hide_emitters)) {
                    Float emitter_pdf = 1.f;
                    if (!count_direct) {
                        DirectionSample3f ds(scene, si, last_scatter_event);
                        emitter_pdf = scene->pdf_emitter_direction(last_scatter_event, ds, true);
                    }
                    Spectrum emitted = emitter->eval(si, true);
                    path.on_emission(emitter, emitted,
                                     count_direct ? Float(1.f)
                                                  : fluo_detail::mis_weight(last_scatter_direction_pdf, emitter_pdf));
                }
            }
            active_surface &= si.is_valid();
            if (active_surface) {
                BSDFPtr bsdf = si.bsdf(ray);
                if (!m_wrappers.empty())
                    bsdf = m_wrappers.resolve(bsdf, si, sampler);
                auto vertex = path.begin_vertex(bsdf, si, sampler);

                // ------------------------ Emitter sampling -----------------
                EmitterSample em;
                em.active = has_flag(bsdf->flags(), BSDFFlags::Smooth) && (depth + 1 < (uint32_t) m_max_depth);
                if (em.active) {
                    auto [emitted, ds] = sample_emitter(si, scene, sampler, medium, channel);
                    em.ds = ds;
                    em.weight = emitted;
                    em.wo = si.to_local(ds.d);
                }

                // ---------------- Emitter contribution, BSDF sampling ------
                Point2f sample_2 = sampler->next_2d(true); // 2D first, as for the phase function
                // (volpath's arguments, evaluated right to left in the wheel)
                Float sample_1 = sampler->next_1d(true);
                BSDFSample3f bs = path.scatter(vertex, bsdf, si, em, sample_1, sample_2);
                eta *= bs.eta;
                ray = si.spawn_ray(si.to_world(bs.wo)); // carries shifted wavelengths, if any
                needs_intersection = true;

                Bool non_null_bsdf = !has_flag(bs.sampled_type, BSDFFlags::Null);
                if (non_null_bsdf) {
                    depth += 1;
                    last_scatter_event = Interaction3f(si);
                    last_scatter_direction_pdf = bs.pdf;
                    valid_ray = true;
                }
                specular_chain |= non_null_bsdf && has_flag(bs.sampled_type, BSDFFlags::Delta);
                specular_chain &= !has_flag(bs.sampled_type, BSDFFlags::Smooth);
                if (si.is_medium_transition())
                    medium = si.target_medium(ray.d);
            }
            active &= (active_surface || active_medium);
        }
        return { path.radiance(), valid_ray };
    }

    std::string to_string() const override {
        std::ostringstream oss;
        fluo::Range range = m_spectral.range();
        oss << "FluoVolpath[" << std::endl
            << "  max_depth = " << m_max_depth << "," << std::endl
            << "  rr_depth = " << m_rr_depth << "," << std::endl
            << "  lambda_min = " << m_lambda_min << "," << std::endl
            << "  fluorescent_bsdfs = " << m_spectral.size() << "," << std::endl
            << "  fluorescent_media = " << m_media.size() << "," << std::endl
            << "  excitation_range = [" << range.lo << ", " << range.hi << "]" << std::endl
            << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(FluoVolpath)

private:
    /// A fluorescent medium of the scene with the excitation range it can use.
    struct MediumEntry {
        const BMedium *medium;
        fluo::Range range;
    };

    /// The per-wavelength choice at a real collision in a fluorescent medium.
    struct MediumShift {
        bool any = false;
        std::array<bool, 4> shifted{};
        /// Shifted wavelengths see the isotropic 1/(4π) instead of the phase value.
        void apply(Spectrum &phase_val) const {
            if constexpr (is_spectral_v<Spectrum>) {
                for (size_t j = 0; j < 4; ++j)
                    if (shifted[j])
                        phase_val[j] = InvFourPi;
            }
        }
        void apply_weight(Spectrum &phase_weight, Float phase_pdf) const {
            if constexpr (is_spectral_v<Spectrum>) {
                for (size_t j = 0; j < 4; ++j)
                    if (shifted[j])
                        phase_weight[j] = InvFourPi / phase_pdf;
            }
        }
    };

    static double lambda_min_of(const Properties &props) {
        double lambda_min = fluo_detail::get_float(Plugin, props, "lambda_min", 300.0);
        if (!(lambda_min >= LambdaMinLo && lambda_min <= LambdaMinHi))
            Throw("%s: invalid parameter \"lambda_min\" = %f: valid range is [%.0f, %.0f] nm", Plugin, lambda_min,
                  LambdaMinLo, LambdaMinHi);
        return lambda_min;
    }

    const MediumEntry *find_medium(const Medium *m) const {
        if (m_media.empty())
            return nullptr;
        auto it = m_media.find(static_cast<const void *>(m));
        return it == m_media.end() ? nullptr : &it->second;
    }

    /// Null and real collision probabilities in a fluorescent medium, by spectral tracking
    /// (Kutz et al. 2017): in proportion to max_j |T_j| σn_j and max_j |T_j| σt_j over the
    /// hero wavelengths' throughputs T. Where the first hero wavelength is in the
    /// absorption band and the others are not, volpath's mean rule would keep killing
    /// the transparent ones with it (their transmittance estimate survives n null
    /// collisions with probability ~0.75^n); here, once a wavelength's throughput is 0
    /// it no longer votes. Unbiased: either event has positive probability wherever its
    /// weight is non-zero for some wavelength.
    static std::pair<Float, Float> spectral_tracking(const MediumInteraction3f &mei, const Spectrum &throughput) {
        UnpolarizedSpectrum t = dr::abs(unpolarized_spectrum(throughput));
        Float q_null = dr::max(t * mei.sigma_n), q_real = dr::max(t * mei.sigma_t);
        Float total = q_null + q_real;
        if (!(total > 0.f) || !dr::isfinite(total))
            return { 0.f, 1.f }; // nothing carried: a real collision with weight 0 ends it
        Float p_null = q_null / total;
        return { p_null, 1.f - p_null };
    }

    /// Per hero wavelength: elastic with probability σs/(σs + μf), else a shift to λi
    /// (mei.wavelengths[j] = λi); `sigma_s` becomes σs + μf where the wavelength goes on,
    /// 0 where it cannot.
    MediumShift choose_medium_shift(const MediumEntry &e, MediumInteraction3f &mei, Sampler *sampler,
                                    UnpolarizedSpectrum &sigma_s) const {
        MediumShift shift;
        if constexpr (is_spectral_v<Spectrum>) {
            std::array<float, 4> mu_f{};
            e.medium->shift_coefficients(mei, e.range, mu_f);
            for (size_t j = 0; j < 4; ++j) {
                double lo = mei.wavelengths[j];
                double ss = std::max(0.0, (double) sigma_s[j]);
                double sf = std::max(0.0, (double) mu_f[j]);
                double total = ss + sf;
                Point2f u = sampler->next_2d();
                if (!(total > 0.0) || !std::isfinite(total)) {
                    sigma_s[j] = 0.f;
                    continue;
                }
                sigma_s[j] = (float) total;
                if (u.x() * total < ss)
                    continue; // elastic: weight ss / pe = total
                fluo::Sample s = e.medium->sample_excitation(lo, u.y(), e.range);
                if (!(s.pdf > 0.0)) {
                    sigma_s[j] = 0.f;
                    continue;
                }
                // Shift: weight μa f / ((1 − pe) p) = μf / (1 − pe) = total.
                shift.shifted[j] = true;
                shift.any = true;
                mei.wavelengths[j] = (float) s.value;
            }
        }
        return shift;
    }

    /// Scan the scene once per render: fluorescent media and BSDFs, emitters' range.
    void prepare(Scene *scene) {
        m_wrappers.clear();
        m_media.clear();
        std::vector<const BMedium *> media;
        auto add = [&](const Medium *m) {
            if (auto *b = dynamic_cast<const BMedium *>(m)) {
                b->set_managed(true);
                if (b->fluorescent() && std::find(media.begin(), media.end(), b) == media.end())
                    media.push_back(b);
            }
        };
        for (const auto &shape : scene->shapes()) {
            add(shape->interior_medium());
            add(shape->exterior_medium());
        }
        for (const auto &sensor : scene->sensors())
            add(sensor->medium());

        if constexpr (is_rgb_v<Spectrum>) {
            if (!media.empty())
                Throw("%s: the scene has a fluorescent participating medium, which scalar_rgb cannot "
                      "transport yet (no reduced RGB transport for media): render it in scalar_spectral, "
                      "or set the medium's quantum_yield to 0 for its non-fluorescent limit",
                      Plugin);
            fluo_detail::Collector c;
            for (const auto &shape : scene->shapes())
                c.visit(const_cast<Shape *>(shape.get()));
            for (Object *o : c.objects)
                if (auto *b = dynamic_cast<BispectralBSDF<Float, Spectrum> *>(o); b && b->fluorescence())
                    Throw("%s: the scene has a fluorescent BSDF, which fluo_volpath transports only in "
                          "scalar_spectral: render it in scalar_spectral, or use fluo_path (reduced RGB "
                          "transport) for scenes without participating media",
                          Plugin);
            m_spectral.prepare(scene, m_wrappers, m_lambda_min, Plugin);
            return;
        } else {
            double hi = -1e30;
            for (const BMedium *b : media)
                hi = std::max(hi, b->lambda_range().hi);
            m_spectral.prepare(scene, m_wrappers, m_lambda_min, Plugin, media.empty() ? -1e30 : hi);
            fluo::Range r = m_spectral.range();
            if (scene->emitters().empty())
                return;
            for (const BMedium *b : media) {
                fluo::Range lr = b->lambda_range();
                fluo::Range range{ std::max(lr.lo, r.lo), std::min(lr.hi, r.hi) };
                if (range.lo < range.hi)
                    m_media.emplace(static_cast<const void *>(static_cast<const Medium *>(
                                        dynamic_cast<const Medium *>(b))),
                                    MediumEntry{ b, range });
            }
        }
    }

    /// An emitter sample seen from `ref` and its transmittance through media and null
    /// interfaces (ratio tracking, as volpath's sample_emitter).
    template <typename Interaction>
    std::pair<Spectrum, DirectionSample3f> sample_emitter(const Interaction &ref, const Scene *scene,
                                                         Sampler *sampler, MediumPtr medium,
                                                         uint32_t channel) const {
        Spectrum transmittance(1.0f);
        auto [ds, emitter_val] = scene->sample_emitter_direction(ref, sampler->next_2d(true), false, true);
        if (ds.pdf == 0.f)
            return { Spectrum(0.f), ds };

        Ray3f ray = ref.spawn_ray_to(ds.p);
        Float max_dist = ray.maxt;
        if constexpr (std::is_convertible_v<Interaction, SurfaceInteraction3f>)
            if (ref.is_medium_transition())
                medium = ref.target_medium(ray.d);

        Float total_dist = 0.f;
        SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>();
        MediumInteraction3f mei = dr::zeros<MediumInteraction3f>();
        Bool needs_intersection = true;
        Bool active = true;
        while (active) {
            Float remaining_dist = max_dist - total_dist;
            ray.maxt = remaining_dist;
            active &= remaining_dist > 0.f;
            if (!active)
                break;

            Bool escaped_medium = false;
            Bool active_medium = medium != nullptr;
            Bool active_surface = !active_medium;
            if (active_medium) {
                mei = medium->sample_interaction(ray, sampler->next_1d(true), channel, true);
                if (medium->is_homogeneous() && mei.is_valid())
                    ray.maxt = dr::minimum(mei.t, remaining_dist);
                if (needs_intersection)
                    si = scene->ray_intersect(ray, true);
                if (si.t < mei.t)
                    mei.t = dr::Infinity<Float>;
                needs_intersection = false;

                Bool is_spectral = medium->has_spectral_extinction();
                Bool not_spectral = !is_spectral;
                if (is_spectral) {
                    Float t = dr::minimum(remaining_dist, dr::minimum(mei.t, si.t)) - mei.mint;
                    UnpolarizedSpectrum tr = dr::exp(-t * mei.combined_extinction);
                    UnpolarizedSpectrum free_flight_pdf =
                        dr::select(si.t < mei.t || mei.t > remaining_dist, tr, tr * mei.combined_extinction);
                    Float tr_pdf = free_flight_pdf[channel];
                    transmittance *= dr::select(tr_pdf > 0.f, tr / tr_pdf, 0.f);
                }

                if (mei.t > remaining_dist && mei.is_valid())
                    total_dist = ds.dist;
                if (mei.t > remaining_dist)
                    mei.t = dr::Infinity<Float>;

                escaped_medium = !mei.is_valid();
                active_medium = mei.is_valid();
                is_spectral &= active_medium;
                not_spectral &= active_medium;

                if (active_medium) {
                    total_dist += mei.t;
                    ray.o = mei.p;
                    si.t = si.t - mei.t;
                    if (is_spectral)
                        transmittance *= mei.sigma_n;
                    if (not_spectral)
                        transmittance *= mei.sigma_n / mei.combined_extinction;
                }
            }

            if (active_surface && needs_intersection) {
                si = scene->ray_intersect(ray, true);
                needs_intersection = false;
            }
            active_surface |= escaped_medium;
            if (active_surface)
                total_dist += si.t;

            active_surface &= si.is_valid() && active && !active_medium;
            if (active_surface) {
                const BSDF *bsdf = si.bsdf(ray);
                Spectrum bsdf_val = bsdf->eval_null_transmission(si, true);
                bsdf_val = si.to_world_mueller(bsdf_val, si.wi, si.wi);
                transmittance *= bsdf_val;
                ray = si.spawn_ray(ray.d);
                ray.maxt = remaining_dist;
                needs_intersection = true;
            }

            active &= (active_medium || active_surface) && dr::any(unpolarized_spectrum(transmittance) != 0.f);
            if (active_surface && si.is_medium_transition())
                medium = si.target_medium(ray.d);
        }
        return { emitter_val * transmittance, ds };
    }

    double m_lambda_min;
    Spectral m_spectral;
    fluo_detail::FluoWrappers<Float, Spectrum> m_wrappers;
    std::unordered_map<const void *, MediumEntry> m_media;
};

static const bool fluo_volpath_registered =
    (fluo_detail::register_scalar_plugin<FluoVolpath>("fluo_volpath", ObjectType::Integrator), true);

NAMESPACE_END(mitsuba)
