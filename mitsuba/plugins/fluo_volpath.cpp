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
#include <limits>
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
#include "fluo_transport_reduced.h"
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
 * - basis
   - |string|
   - ``scalar_rgb`` only: transport basis of the reduced transport, ``rgb``, ``xyzu`` or
     ``x7``, as for ``fluo_path`` (whose documentation says which when).
     (Default: ``x7``)
 * - method
   - |string|
   - ``scalar_rgb`` only: reduction, ``ours`` or ``naive``, as for ``fluo_path``.
     (Default: ``ours``)
 * - closed_form_shadows
   - |bool|
   - ``scalar_rgb`` only: shadow rays through a fluorescent medium of constant density
     and scattering take its reduced transfer exp(−(d·A + σs)·t) in closed form
     (diagonalised once per render) instead of ratio tracking it; ``false`` tracks it
     (the reference the tests compare with). Media whose operator cannot be diagonalised
     well (complex or repeated eigenvalues) are tracked either way. (Default: true)

Mitsuba's ``volpath`` (delta tracking with null collisions, next-event estimation
through media with ratio-tracked transmittance, MIS between emitter and phase/BSDF
sampling, index-matched ``null`` boundaries, Russian roulette) in ``scalar_spectral``
and ``scalar_rgb``, extended with fluorescence:

* **in media** that implement fluo's bispectral medium interface (``fluo_qd_medium``):
  at an absorption event the medium re-emits isotropically at a longer wavelength;
* **at surfaces**: everything ``fluo_path`` does for fluo's fluorescent BSDFs
  (``fluo_jung``, ``fluo_qd``, ``fluo_matrix``, ``fluo_gmm``, inside ``twosided``,
  ``blendbsdf``, ``mask``, ``normalmap``, ``bumpmap``), with the same code.

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
vanish, with probability ~0.75^n after n null collisions). Fluorescence also needs
real collisions where the medium is transparent at λo but re-emits there (dots emit
beyond their absorption edge: blue dots seen at 470 nm absorb only below 420 nm): the
real-collision probability is raised to at least κ/μ̄, κ = min(σs + μf, 1/ℓ) over the
carried wavelengths with ℓ the length of the current straight flight, and for that
flight the medium's majorant covers μf up to 1/ℓ as well. That is about one
fluorescent collision per flight, spread along it; the transmitted wavelengths' null
weights grow by at most ~e over it. (Without it such a glow came from real collisions
near where other hero wavelengths were absorbed only: ~9x too dark, test02b.) At a
real collision, for each λo the radiative transfer equation's source is

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
most opaque hero wavelength (the medium's absorption and re-emission coefficients at a
path's wavelengths are looked up once per flight and per thread, not per collision):
optically thick fluorescent media (τ ≫ 100 over the scene) render slowly; fluorescence
itself costs one excitation sample per shifted wavelength at real collisions, and the
paths it continues (re-emitted light goes on where volpath's absorbed light stops).

**Reduced RGB transport (scalar_rgb).** With fluorescent media or BSDFs in the scene,
``scalar_rgb`` carries fluo_path's reduced transport (its ``basis``: K bands; the RGB
throughput t until the first fluorescent event, then the 3×K matrix R). A fluorescent
medium acts on the K basis coefficients through two K×K operators that Rust reduces at
render start from its spectra (``fluo::medium_reduced``): its absorption A (the
reduction of the diagonal μa(λ)) and its reradiation F (of μa(λi) f(λi → λo)), per
unit density. Tracking uses the medium's majorant μ̄ (in RGB: over the bands, the largest
diagonal entry of A, at least μa's RGB channels; any μ̄ > 0 would do) with matrix
weights, exact for the
reduced operators: a null collision multiplies R by (μ̄ − σs − d·A)/(μ̄ p_null), a
real one by the collision's source σs·p + d·F/(4π) over μ̄ p_real (p: the phase
function's value, or weight with the sampled direction; d: the density there), with the
probabilities of spectral tracking over R's columns (bands instead of wavelengths,
the same fluorescent-source rule). Shadow rays through fluorescent media carry their
transmittance as the list of those null operators, applied to the emitter's basis
coefficients at the end (K² per collision); through a medium of constant density and
scattering the segment's transfer is exp(−(d·A + diag σs)·t) = V·diag(e^{−λt})·V⁻¹ in
closed form instead (``closed_form_shadows``; Rust diagonalises the operator once per
render and refuses complex, repeated or negative eigenvalues and ill-conditioned V, where
tracking stays): the same expectation (test05d) with less noise, ~6 % faster. Native
media and null interfaces act on R through their RGB weights' per-band factors, as native BSDFs do in fluo_path.
Accuracy: that of the basis (the dots' glow in a thin 2 cm cube under D65 within 3 %
of the spectral reference with ``x7`` and ``xyzu``, test05), plus the reduction of
attenuation itself: exp(−d·A·t) is not the reduction of exp(−μa(λ) t), so optically
thick media (τ ≳ 1 over their colour) lose their transmission windows as native RGB
media do (the same cube at thirty times that density, τ ≈ 1 in the green: 8 % under
the spectral red). Under narrow UV lamps one UV band averages the absorption over
300-400 nm (the basis's warning applies; the cuvettes of blue- to red-emitting dots under
a 300-380 nm lamp came out within 16 % of the spectral render here, but a narrow
365 nm line can be off several-fold).

**Variants.** ``scalar_spectral`` (wavelength shifting) and ``scalar_rgb`` (reduced
transport); without fluorescence both render exactly as ``volpath``. ``llvm_ad_spectral``
and ``llvm_ad_rgb`` (and ``cuda_ad_*``, the same code) run the same estimators in one
vectorised kernel (``fluo_volpath_jit.cpp``; the media interpolate Rust's tables of μa and
the emission, ``fluo_medium_jit.h``; the reduced transport and the fluorescent BSDFs'
matrices are fluo_path's, ``fluo_jit_reduced.h``): the same images within noise
(tests/python/test_llvm.py test16). Differences of those variants: the μa table of a dye
medium is linear between 4096 nodes across its absorption band (within 3e-7 of its peak),
shadow rays always ratio-track (``closed_form_shadows`` has no effect there; in RGB a
shadow ray multiplies the vertex's 3×K row block by each null operator, 3K² per
collision, instead of keeping the list), and a path's random numbers differ. Without
fluorescence the vectorised variants hand the render to Mitsuba's own ``volpath`` (the
same image, seed for seed).

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
    using Reduced = ReducedTransport<Float, Spectrum>;
    using Square = typename Reduced::Square;
    using Coeffs = typename Reduced::Coeffs;

    static constexpr const char *Plugin = "fluo_volpath";
    static constexpr float InvFourPi = fluo_detail::InvFourPi;

    FluoVolpath(const Properties &props)
        : Base(props), m_lambda_min(fluo_detail::lambda_min_of(Plugin, props)),
          m_reduced(Plugin, fluo_detail::get_string(props, "basis", "x7"),
                    fluo_detail::get_string(props, "method", "ours")),
          m_closed_shadows(props.get<bool>("closed_form_shadows", true)) {}

    using Base::render;
    TensorXf render(Scene *scene, Sensor *sensor, UInt32 seed, uint32_t spp, bool develop,
                    bool evaluate) override {
        prepare(scene);
        return Base::render(scene, sensor, seed, spp, develop, evaluate);
    }

    std::pair<Spectrum, Bool> sample(const Scene *scene, Sampler *sampler, const RayDifferential3f &ray_,
                                     const Medium *initial_medium, Float * /* aovs */,
                                     Bool active) const override {
        if constexpr (is_rgb_v<Spectrum>) {
            if (m_use_reduced) {
                typename Reduced::Path path(m_reduced);
                return trace(scene, sampler, ray_, initial_medium, active, path);
            }
        }
        Path path(m_spectral);
        return trace(scene, sampler, ray_, initial_medium, active, path);
    }

    /// volpath's loop; `path` is fluo_path's spectral transport (every variant without
    /// fluorescence, and scalar_spectral) or its reduced transport (scalar_rgb with
    /// fluorescence), whose fluorescent media act on basis coefficients.
    template <typename PathT>
    std::pair<Spectrum, Bool> trace(const Scene *scene, Sampler *sampler, const RayDifferential3f &ray_,
                                    const Medium *initial_medium, Bool active, PathT &path) const {
        constexpr bool IsReduced = !std::is_same_v<PathT, Path>;
        // A wavelength-preserving weight.
        auto scale = [&path](const Spectrum &w) {
            if constexpr (IsReduced)
                path.scale(w);
            else
                path.throughput() *= w;
        };
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
        double flight_inv_len = 0.0;
        // A flight through a fluorescent medium: its surface hit, not yet a full interaction
        // (si.t alone is kept, as volpath keeps it, until the flight reaches the surface).
        PreliminaryIntersection3f pending_pi = dr::zeros<PreliminaryIntersection3f>();
        Ray3f pending_ray = ray;
        bool pending = false;

        while (active) {
            // ----------------- Russian roulette, max_depth -----------------
            if constexpr (IsReduced) {
                double t_max = path.throughput_max();
                active &= t_max != 0.0;
                Float q = dr::minimum((Float) t_max * dr::square(eta), .95f);
                Bool perform_rr = depth > (uint32_t) m_rr_depth;
                active &= sampler->next_1d(active) < q || !perform_rr;
                if (perform_rr)
                    path.roulette(q);
            } else {
                Spectrum &throughput = path.throughput();
                active &= dr::any(unpolarized_spectrum(throughput) != 0.f);
                Float q = dr::minimum(dr::max(unpolarized_spectrum(throughput)) * dr::square(eta), .95f);
                Bool perform_rr = depth > (uint32_t) m_rr_depth;
                active &= sampler->next_1d(active) < q || !perform_rr;
                if (perform_rr)
                    throughput *= dr::rcp(q);
            }
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
            const ReducedMedium *rmed = nullptr; // reduced: a fluorescent medium
            Collision col;                       // reduced: its real collision
            if (active_medium) {
                is_spectral = medium->has_spectral_extinction();
                not_spectral = !is_spectral;
                // A fluorescent medium: its entry in the spectral or the reduced transport.
                if constexpr (IsReduced)
                    rmed = find_reduced(medium);
                else
                    fluo_entry = find_medium(medium);
                bool fluorescent_here = fluo_entry || rmed;
                if (fluorescent_here && needs_intersection) {
                    // Only the distance is read until the flight ends at the surface: the
                    // full interaction is computed then (most flights end in the medium).
                    pending_pi = scene->ray_intersect_preliminary(ray, true, false, 0, 0, true);
                    pending_ray = ray;
                    pending = true;
                    si = dr::zeros<SurfaceInteraction3f>();
                    si.t = pending_pi.t;
                    needs_intersection = false;
                    // 1/ℓ for the flight that starts here (ℓ: its length to the next
                    // surface; 0 without one): the fluorescent source is sampled at rate
                    // up to 1/ℓ (spectral_tracking), and the majorant covers it.
                    flight_inv_len = si.is_valid() ? 1.0 / std::max((double) si.t, 1e-30) : 0.0;
                }
                {
                    fluo_detail::ScopedSourceRate rate(
                        !fluorescent_here ? 0.0
                                          : (flight_inv_len > 0.0 ? flight_inv_len
                                                                   : std::numeric_limits<double>::infinity()));
                    mei = medium->sample_interaction(ray, sampler->next_1d(active_medium), channel, active_medium);
                }
                if (medium->is_homogeneous() && mei.is_valid())
                    ray.maxt = mei.t;
                if (needs_intersection)
                    si = scene->ray_intersect(ray, true);
                needs_intersection = false;
                if (si.t < mei.t)
                    mei.t = dr::Infinity<Float>;
                // (a fluorescent medium's majorant is one for all bands: weight 1 to escape,
                // 1/μ̄ at a tentative collision, applied below)
                if (is_spectral && !rmed) {
                    auto [tr, free_flight_pdf] = medium->transmittance_eval_pdf(mei, si, true);
                    Float tr_pdf = free_flight_pdf[channel];
                    scale(dr::select(tr_pdf > 0.f, tr / tr_pdf, 0.f));
                }
                escaped_medium = !mei.is_valid();
                active_medium = mei.is_valid();
                is_spectral &= active_medium;
                not_spectral &= active_medium;
                if (active_medium) {
                    // Null or real: volpath's rule (the hero wavelengths' mean null
                    // probability), or spectral tracking in fluorescent media (over the
                    // bands' columns of R in the reduced transport).
                    if constexpr (IsReduced) {
                        if (rmed) {
                            path.to_reduced();
                            col = collision(*rmed, mei);
                            std::tie(null_scatter_prob, real_scatter_prob) =
                                band_tracking(*rmed, col, path.column_max(), flight_inv_len);
                        }
                    }
                    if (rmed) {
                        // (set above)
                    } else if (fluo_entry && is_spectral) {
                        if constexpr (!IsReduced) {
                            std::array<float, 4> bound{};
                            fluo_entry->medium->source_bound(mei, bound);
                            std::tie(null_scatter_prob, real_scatter_prob) =
                                spectral_tracking(mei, path.throughput(), bound, flight_inv_len);
                        }
                    } else {
                        null_scatter_prob = dr::mean(mei.sigma_n / mei.combined_extinction);
                        real_scatter_prob = dr::mean(mei.sigma_t / mei.combined_extinction);
                    }
                    Bool null_scatter = sampler->next_1d(active_medium) < null_scatter_prob;
                    act_null_scatter = null_scatter;
                    act_medium_scatter = !null_scatter;
                    if constexpr (IsReduced) {
                        if (rmed && act_null_scatter) { // R ← R·(μ̄ − σs − d·A)/(μ̄ p_null)
                            Coeffs g{};
                            for (size_t k = 0; k < m_reduced.bands(); ++k)
                                g[k] = col.majorant - col.sigma_s[k];
                            path.multiply_null(rmed->a, col.density, g,
                                               1.0 / (col.majorant * (double) null_scatter_prob));
                        }
                    }
                    if (is_spectral && act_null_scatter && !rmed)
                        scale(mei.sigma_n / null_scatter_prob);
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
                if (fluo_entry && !IsReduced)
                    shift = choose_medium_shift(*fluo_entry, mei, sampler, sigma_s);

                // A fluorescent medium's real collision (reduced): the source operator
                // W = σs·p + d·F/(4π) over μ̄ p_real, applied with the direction below.
                double real_scale = rmed ? 1.0 / (col.majorant * (double) real_scatter_prob) : 1.0;
                if (is_spectral && !rmed)
                    scale(sigma_s / real_scatter_prob);
                if (not_spectral)
                    scale(sigma_s / mei.sigma_t);
                if constexpr (!IsReduced) {
                    // In a fluorescent medium, a collision that absorbed every wavelength for
                    // good (none scatters or shifts) ends the path here, before an emitter
                    // sample it could only weigh by 0 (volpath's own media keep volpath's
                    // steps, random numbers included).
                    if (fluo_entry && !dr::any(unpolarized_spectrum(path.throughput()) != 0.f))
                        break;
                }

                PhaseFunctionContext phase_ctx(sampler);
                const auto *phase = mei.medium->phase_function();

                // ------------------------ Emitter sampling -----------------
                Bool sample_emitters = mei.medium->use_emitter_sampling();
                valid_ray = true;
                specular_chain = !sample_emitters;
                if (sample_emitters) {
                    Shadow shadow;
                    auto [emitted, ds] =
                        sample_emitter(mei, scene, sampler, medium, channel, IsReduced ? &shadow : nullptr);
                    auto [phase_val, phase_pdf] = phase->eval_pdf(phase_ctx, mei, ds.d, true);
                    Float mis = fluo_detail::mis_weight(ds.pdf, dr::select(ds.delta, 0.f, phase_pdf));
                    if constexpr (IsReduced) {
                        Coeffs c{};
                        if (shadow.active || rmed)
                            c = shadow_light(shadow, m_reduced.emitter_coefficients(ds.emitter, emitted));
                        if (rmed)
                            path.add(source_matrix(*rmed, col, phase_val, InvFourPi), c, real_scale * (double) mis);
                        else
                            path.add_light(phase_val, ds.emitter, emitted, shadow.active ? &c : nullptr,
                                           (double) mis);
                    } else {
                        shift.apply(phase_val);
                        path.add_radiance(phase_val * emitted * mis);
                    }
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
                    if constexpr (IsReduced) {
                        if (rmed)
                            path.multiply(source_matrix(*rmed, col, phase_weight, InvFourPi / (double) phase_pdf),
                                          real_scale);
                    }
                    if (!rmed)
                        scale(phase_weight);
                }
            }

            // ----------------------- Surface interactions ------------------
            active_surface |= escaped_medium;
            if (pending && active_surface && !needs_intersection) {
                Float t = si.t; // (shortened by the flight's null collisions)
                si = pending_pi.compute_surface_interaction(pending_ray, +RayFlags::All, true);
                si.t = t;
                pending = false;
            }
            if (needs_intersection) // a new ray: the flight ended at a collision
                pending = false;
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
                typename fluo_detail::FluoWrappers<Float, Spectrum>::Perturbations perturbed;
                if (!m_wrappers.empty())
                    bsdf = m_wrappers.resolve(bsdf, si, sampler, perturbed);
                auto vertex = path.begin_vertex(bsdf, si, sampler);

                // ------------------------ Emitter sampling -----------------
                EmitterSample em;
                em.active = has_flag(bsdf->flags(), BSDFFlags::Smooth) && (depth + 1 < (uint32_t) m_max_depth);
                Shadow shadow;
                if (em.active) {
                    auto [emitted, ds] =
                        sample_emitter(si, scene, sampler, medium, channel, IsReduced ? &shadow : nullptr);
                    em.ds = ds;
                    em.weight = emitted;
                    em.wo = si.to_local(ds.d);
                    em.active &= perturbed.keeps_side(ds.d);
                }
                Coeffs light;
                if constexpr (IsReduced) {
                    if (shadow.active)
                        light = shadow_light(shadow, m_reduced.emitter_coefficients(em.ds.emitter, em.weight));
                    path.set_light(shadow.active ? &light : nullptr);
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
                if (!perturbed.keeps_side(ray.d)) // a normal or bump map's sample across the surface: no weight
                    break;
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

    /// A shadow ray's transfer through fluorescent media (reduced transport): its
    /// operators T_i = diag(g) − d·A in the ray's order from the vertex, applied to the
    /// emitter's coefficients c at the end, T_1·(T_2·(…·c)) at K² each (multiplying
    /// them out as they come would cost K³ each); beyond Capacity they are multiplied
    /// out into p.
    struct Shadow {
        using Coeffs = typename ReducedTransport<Float, Spectrum>::Coeffs;
        using Square = typename ReducedTransport<Float, Spectrum>::Square;
        /// diag(g) − d·A; or, with v set, the closed-form transfer V·diag(g)·V⁻¹.
        struct Op {
            const Square *a; ///< nullptr: diagonal only
            double d;
            Coeffs g;
            const Square *v = nullptr, *v_inv = nullptr;
        };
        static constexpr size_t Capacity = 32;
        bool active = false; ///< a fluorescent medium was met: the light is light(c)
        size_t n = 0;
        std::array<Op, Capacity> ops;
        bool folded = false; ///< p holds the operators before ops
        Square p;            ///< (set when folded)
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

    const MediumEntry *find_medium(const Medium *m) const {
        if (m_media.empty())
            return nullptr;
        auto it = m_media.find(static_cast<const void *>(m));
        return it == m_media.end() ? nullptr : &it->second;
    }

    /// Null and real collision probabilities in a fluorescent medium. Spectral tracking
    /// (Kutz et al. 2017): in proportion to max_j |T_j| σn_j and max_j |T_j| σt_j over the
    /// hero wavelengths' throughputs T. Where the first hero wavelength is in the
    /// absorption band and the others are not, volpath's mean rule would keep killing
    /// the transparent ones with it (their transmittance estimate survives n null
    /// collisions with probability ~0.75^n); here, once a wavelength's throughput is 0 it
    /// no longer votes. Then p_real is raised to at least min(κ/μ̄, 1/2), κ = max_j
    /// min(σs_j + μf_j, 1/ℓ) over the carried wavelengths (μf: the medium's
    /// source_bound; ℓ: the length of the current straight flight, no cap without a
    /// surface ahead): a real collision's weight (σs + μf)/(μ̄ p_real) is non-zero where
    /// the medium re-emits at λo also where it is transparent at λo (blue dots seen at
    /// 470 nm absorb only below 420 nm: μf(λo) > 0 = σt(λo)). With σt alone such
    /// collisions happened only near where other hero wavelengths were absorbed and the
    /// glow came out ~9x too dark. At rate ≤ 1/ℓ (the majorant covers it: fluo_volpath
    /// asks the medium for it, fluo_detail::ScopedSourceRate) this makes about one
    /// fluorescent collision per flight, spread along it, and the transparent
    /// wavelengths' null weights grow by at most ~e over the flight. Unbiased: either
    /// event has positive probability wherever its weight is non-zero for a carried
    /// wavelength (p_null stays ≥ 1/2 unless every carried σn is 0).
    static std::pair<Float, Float> spectral_tracking(const MediumInteraction3f &mei, const Spectrum &throughput,
                                                     const std::array<float, 4> &source_bound, double inv_len) {
        UnpolarizedSpectrum t = dr::abs(unpolarized_spectrum(throughput));
        double q_null = (double) dr::max(t * mei.sigma_n), q_real = (double) dr::max(t * mei.sigma_t);
        double kappa = 0.0;
        for (size_t j = 0; j < dr::size_v<UnpolarizedSpectrum> && j < 4; ++j) {
            if (!(t[j] > 0.f))
                continue;
            kappa = std::max(kappa, source_rate(std::max(0.0, (double) mei.sigma_s[j]) +
                                                    std::max(0.0, (double) source_bound[j]),
                                                inv_len));
        }
        return collision_probabilities(q_null, q_real, kappa, (double) dr::max(mei.combined_extinction));
    }

    /// The rate at which a flight samples a source (σs + μf) for its real collisions: the
    /// source capped at 1/ℓ (inv_len), uncapped without a surface ahead (inv_len = 0).
    static double source_rate(double source, double inv_len) {
        return inv_len > 0.0 ? std::min(source, inv_len) : source;
    }

    /// (p_null, p_real) from the tracking weights q_null, q_real and the source rate κ
    /// (spectral_tracking; band_tracking for the reduced transport).
    static std::pair<Float, Float> collision_probabilities(double q_null, double q_real, double kappa,
                                                           double majorant) {
        double total = q_null + q_real;
        if (!(total > 0.0) || !std::isfinite(total))
            return { 0.f, 1.f }; // nothing carried: a real collision with weight 0 ends it
        double p_real = q_real / total;
        if (majorant > 0.0 && std::isfinite(majorant))
            p_real = std::max(p_real, std::min(kappa / majorant, 0.5));
        p_real = std::clamp(p_real, 0.0, 1.0);
        return { (Float) (1.0 - p_real), (Float) p_real };
    }

    /// Per hero wavelength: elastic with probability σs/(σs + μf), else a shift to λi
    /// (mei.wavelengths[j] = λi); `sigma_s` becomes σs + μf where the wavelength goes on,
    /// 0 where it cannot.
    MediumShift choose_medium_shift(const MediumEntry &e, MediumInteraction3f &mei, Sampler *sampler,
                                    UnpolarizedSpectrum &sigma_s) const {
        MediumShift shift;
        if constexpr (is_spectral_v<Spectrum>) {
            std::array<Point2f, 4> us;
            std::array<double, 4> xi{};
            for (size_t j = 0; j < 4; ++j) {
                us[j] = sampler->next_2d();
                xi[j] = (double) us[j].y();
            }
            std::array<float, 4> mu_f{};
            std::array<fluo::Sample, 4> samples;
            e.medium->shift_and_sample(mei, e.range, xi, mu_f, samples);
            for (size_t j = 0; j < 4; ++j) {
                double ss = std::max(0.0, (double) sigma_s[j]);
                double sf = std::max(0.0, (double) mu_f[j]);
                double total = ss + sf;
                const Point2f &u = us[j];
                if (!(total > 0.0) || !std::isfinite(total)) {
                    sigma_s[j] = 0.f;
                    continue;
                }
                sigma_s[j] = (float) total;
                if (u.x() * total < ss)
                    continue; // elastic: weight ss / pe = total
                const fluo::Sample &s = samples[j];
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

    // ------------------ scalar_rgb: reduced transport in fluorescent media -----------

    /// A fluorescent medium's reduced operators A and F, per scene unit at density 1.
    struct ReducedMedium {
        const BMedium *medium;
        Square a{}, f{};
        Coeffs f_rows{}; ///< Σ_i |F_ki| / (4π): the re-emission into band k per unit density
        /// Constant density and scattering: d·A + diag(σs) = V·diag(λ)·V⁻¹, so that a
        /// shadow ray's transfer over t is V·diag(e^{−λt})·V⁻¹ (closed_form_shadows).
        bool closed = false;
        Square v{}, v_inv{};
        Coeffs lambda{};
    };
    /// A tentative collision in a fluorescent medium: density, per-band σs, majorant μ̄.
    struct Collision {
        double density = 0.0, majorant = 1.0;
        Coeffs sigma_s{};
    };

    const ReducedMedium *find_reduced(const Medium *m) const {
        if (m_rmedia.empty() || m == nullptr)
            return nullptr;
        auto it = m_rmedia.find(static_cast<const void *>(m));
        return it == m_rmedia.end() ? nullptr : &it->second;
    }

    Collision collision(const ReducedMedium &r, const MediumInteraction3f &mei) const {
        Collision c;
        c.density = std::max(0.0, (double) r.medium->density_at(mei));
        c.majorant = (double) dr::max(mei.combined_extinction);
        c.sigma_s = m_reduced.band_albedo(Spectrum(mei.sigma_s));
        return c;
    }

    /// Null and real probabilities over the bands, as spectral_tracking over the hero
    /// wavelengths: the bands R carries (w_k = column_max of R) take the wavelengths'
    /// place, in proportion to max_k w_k |μ̄ − σt_k| and max_k w_k σt_k (σt_k = d·A_kk +
    /// σs_k), with the source rate min(σs_k + d·Σ_i |F_ki|/(4π), 1/ℓ) (band k of R meets
    /// row k of the collision's operators). The weights are exact whatever the split.
    std::pair<Float, Float> band_tracking(const ReducedMedium &r, const Collision &c, const Coeffs &w,
                                          double inv_len) const {
        size_t k = m_reduced.bands();
        double q_null = 0.0, q_real = 0.0, kappa = 0.0;
        for (size_t i = 0; i < k; ++i) {
            if (!(w[i] > 0.0))
                continue;
            double st = std::max(0.0, c.density * r.a[i * k + i] + c.sigma_s[i]);
            q_null = std::max(q_null, w[i] * std::abs(c.majorant - st));
            q_real = std::max(q_real, w[i] * st);
            kappa = std::max(kappa, source_rate(std::max(0.0, c.sigma_s[i]) + c.density * r.f_rows[i], inv_len));
        }
        return collision_probabilities(q_null, q_real, kappa, c.majorant);
    }

    /// diag(σs ∘ p) + d·F·iso: the collision's source for an elastic weight p (phase
    /// value or weight) and the isotropic re-emission's iso (1/4π, over the pdf if sampled).
    Square source_matrix(const ReducedMedium &r, const Collision &c, const Spectrum &p, double iso) const {
        size_t k = m_reduced.bands();
        Coeffs pk = m_reduced.band_albedo(p);
        Square w{};
        for (size_t i = 0; i < k * k; ++i)
            w[i] = c.density * r.f[i] * iso;
        for (size_t i = 0; i < k; ++i)
            w[i * k + i] += c.sigma_s[i] * pk[i];
        return w;
    }

    /// p ← p·n·s (K×K).
    void multiply(Square &p, const Square &n, double s) const {
        size_t k = m_reduced.bands();
        Square out{};
        for (size_t i = 0; i < k; ++i)
            for (size_t j = 0; j < k; ++j) {
                double acc = 0.0;
                for (size_t l = 0; l < k; ++l)
                    acc += p[i * k + l] * n[l * k + j];
                out[i * k + j] = acc * s;
            }
        p = out;
    }

    /// Move a shadow ray's RGB transmittance t so far into its transfer (a diagonal
    /// operator of t's band factors, unless t = 1), and mark the transfer active; t ← 1.
    void flush(Shadow &shadow, Spectrum &t) const {
        shadow.active = true;
        if (dr::all(t == 1.f))
            return;
        push(shadow, typename Shadow::Op{ nullptr, 0.0, m_reduced.band_albedo(t) });
        t = Spectrum(1.f);
    }

    /// Append an operator to a shadow ray's transfer (multiplying the list out into p
    /// when it is full).
    void push(Shadow &shadow, const typename Shadow::Op &op) const {
        if (shadow.n == Shadow::Capacity) {
            size_t k = m_reduced.bands();
            if (!shadow.folded) {
                shadow.p.fill(0.0);
                for (size_t i = 0; i < k; ++i)
                    shadow.p[i * k + i] = 1.0;
                shadow.folded = true;
            }
            for (size_t i = 0; i < shadow.n; ++i) {
                const auto &o = shadow.ops[i];
                Square m{};
                if (o.v) {
                    for (size_t r = 0; r < k; ++r)
                        for (size_t c = 0; c < k; ++c)
                            for (size_t j = 0; j < k; ++j)
                                m[r * k + c] += (*o.v)[r * k + j] * o.g[j] * (*o.v_inv)[j * k + c];
                } else {
                    for (size_t j = 0; j < k * k; ++j)
                        m[j] = o.a ? -o.d * (*o.a)[j] : 0.0;
                    for (size_t j = 0; j < k; ++j)
                        m[j * k + j] += o.g[j];
                }
                multiply(shadow.p, m, 1.0);
            }
            shadow.n = 0;
        }
        shadow.ops[shadow.n++] = op;
    }

    /// A shadow ray's transfer applied to light c: T_1·(T_2·(…·c)), K² per operator.
    Coeffs shadow_light(const Shadow &shadow, Coeffs c) const {
        size_t k = m_reduced.bands();
        for (size_t i = shadow.n; i-- > 0;) {
            const auto &o = shadow.ops[i];
            Coeffs out{};
            if (o.v) { // V·diag(g)·V⁻¹·c
                Coeffs y{};
                for (size_t r = 0; r < k; ++r) {
                    for (size_t j = 0; j < k; ++j)
                        y[r] += (*o.v_inv)[r * k + j] * c[j];
                    y[r] *= o.g[r];
                }
                for (size_t r = 0; r < k; ++r)
                    for (size_t j = 0; j < k; ++j)
                        out[r] += (*o.v)[r * k + j] * y[j];
                c = out;
                continue;
            }
            for (size_t r = 0; r < k; ++r) {
                double acc = o.g[r] * c[r];
                if (o.a)
                    for (size_t j = 0; j < k; ++j)
                        acc -= o.d * (*o.a)[r * k + j] * c[j];
                out[r] = acc;
            }
            c = out;
        }
        if (shadow.folded) {
            Coeffs out{};
            for (size_t r = 0; r < k; ++r)
                for (size_t j = 0; j < k; ++j)
                    out[r] += shadow.p[r * k + j] * c[j];
            c = out;
        }
        return c;
    }

    /// Scan the scene once per render: fluorescent media and BSDFs, emitters' range.
    void prepare(Scene *scene) {
        m_wrappers.clear();
        m_media.clear();
        std::vector<const BMedium *> media;
        for (const BMedium *b : fluo_detail::managed_media<BMedium>(scene))
            if (b->fluorescent())
                media.push_back(b);

        if constexpr (is_rgb_v<Spectrum>) {
            // Reduced transport when anything fluoresces, else volpath.
            m_rmedia.clear();
            size_t k = m_reduced.bands();
            for (const BMedium *b : media) {
                ReducedMedium r{ b, {}, {}, {} };
                b->reduced_operators(m_reduced.basis(), rust::Slice<double>(r.a.data(), k * k),
                                     rust::Slice<double>(r.f.data(), k * k));
                double a_max = 0.0;
                for (size_t i = 0; i < k; ++i) {
                    a_max = std::max(a_max, r.a[i * k + i]);
                    for (size_t j = 0; j < k; ++j)
                        r.f_rows[i] += std::abs(r.f[i * k + j]) * InvFourPi;
                }
                b->set_band_absorption_max(a_max);
                MediumInteraction3f at = dr::zeros<MediumInteraction3f>();
                UnpolarizedSpectrum sigma_t;
                const Medium *medium = dynamic_cast<const Medium *>(b);
                if (m_closed_shadows && b->constant_extinction(at, sigma_t)) {
                    auto [sigma_s, sigma_n, sigma_tt] = medium->get_scattering_coefficients(at, true);
                    double d = std::max(0.0, (double) b->density_at(at));
                    Coeffs s = m_reduced.band_albedo(Spectrum(sigma_s));
                    Square m{};
                    for (size_t i = 0; i < k; ++i) {
                        for (size_t j = 0; j < k; ++j)
                            m[i * k + j] = d * r.a[i * k + j];
                        m[i * k + i] += s[i];
                    }
                    r.closed = fluo::reduced_eigen(rust::Slice<const double>(m.data(), k * k),
                                                   rust::Slice<double>(r.v.data(), k * k),
                                                   rust::Slice<double>(r.v_inv.data(), k * k),
                                                   rust::Slice<double>(r.lambda.data(), k));
                }
                m_rmedia.emplace(static_cast<const void *>(medium), r);
            }
            m_reduced.prepare(scene, m_wrappers, !media.empty());
            m_use_reduced = m_reduced.active() || !m_rmedia.empty();
            if (!m_use_reduced) {
                m_wrappers.clear();
                m_spectral.prepare(scene, m_wrappers, m_lambda_min, Plugin);
            }
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
    /// With the reduced transport, fluorescent media on the way act on basis
    /// coefficients: `shadow` then receives the ray's K×K transfer (everything after the
    /// first such medium is in it; the returned radiance is then the emitter's alone).
    template <typename Interaction>
    std::pair<Spectrum, DirectionSample3f> sample_emitter(const Interaction &ref, const Scene *scene,
                                                         Sampler *sampler, MediumPtr medium, uint32_t channel,
                                                         Shadow *shadow) const {
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
            // A fluorescent medium whose extinction is the same everywhere: its
            // transmittance to the next surface in closed form, exp(−σt·t) per
            // wavelength, instead of ratio tracking's ~μ̄·t steps (scalar_spectral).
            const MediumEntry *constant_entry = active_medium ? find_medium(medium) : nullptr;
            UnpolarizedSpectrum constant_sigma_t(0.f);
            if (constant_entry) {
                MediumInteraction3f at = dr::zeros<MediumInteraction3f>();
                at.wavelengths = ray.wavelengths;
                at.p = ray.o;
                if (!constant_entry->medium->constant_extinction(at, constant_sigma_t))
                    constant_entry = nullptr;
            }
            // The same in reduced transport: the K×K transfer V·diag(e^{−λt})·V⁻¹.
            const ReducedMedium *closed = shadow && m_use_reduced && active_medium ? find_reduced(medium) : nullptr;
            if (closed && !closed->closed)
                closed = nullptr;

            if (constant_entry || closed) {
                if (needs_intersection)
                    si = scene->ray_intersect(ray, true);
                needs_intersection = false;
                bool reaches_surface = si.is_valid() && si.t < remaining_dist;
                double t = (double) (reaches_surface ? si.t : remaining_dist);
                if (closed) {
                    flush(*shadow, transmittance);
                    typename Shadow::Op op{ nullptr, 0.0, {}, &closed->v, &closed->v_inv };
                    for (size_t j = 0; j < m_reduced.bands(); ++j)
                        op.g[j] = std::exp(-closed->lambda[j] * t);
                    push(*shadow, op);
                } else {
                    transmittance *= dr::exp(-(Float) t * constant_sigma_t);
                }
                if (!reaches_surface)
                    break; // the emitter lies inside this medium
                escaped_medium = true;
                active_medium = false;
            } else if (active_medium) {
                mei = medium->sample_interaction(ray, sampler->next_1d(true), channel, true);
                if (medium->is_homogeneous() && mei.is_valid())
                    ray.maxt = dr::minimum(mei.t, remaining_dist);
                if (needs_intersection)
                    si = scene->ray_intersect(ray, true);
                if (si.t < mei.t)
                    mei.t = dr::Infinity<Float>;
                needs_intersection = false;

                const ReducedMedium *rmed = shadow && m_use_reduced ? find_reduced(medium) : nullptr;
                Bool is_spectral = medium->has_spectral_extinction();
                Bool not_spectral = !is_spectral;
                if (is_spectral && !rmed) {
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
                    if (rmed) { // ratio tracking on coefficients: T = (μ̄ − σs − d·A)/μ̄
                        Collision c = collision(*rmed, mei);
                        flush(*shadow, transmittance);
                        typename Shadow::Op op{ &rmed->a, c.density / c.majorant, {} };
                        for (size_t k = 0; k < m_reduced.bands(); ++k)
                            op.g[k] = (c.majorant - c.sigma_s[k]) / c.majorant;
                        push(*shadow, op);
                    } else if (is_spectral)
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
        if (shadow && shadow->active) {
            flush(*shadow, transmittance);
            return { emitter_val, ds };
        }
        return { emitter_val * transmittance, ds };
    }

    double m_lambda_min;
    Spectral m_spectral;
    Reduced m_reduced; ///< scalar_rgb with fluorescence (the basis is checked in both variants)
    bool m_use_reduced = false;
    bool m_closed_shadows = true; ///< closed_form_shadows
    std::unordered_map<const void *, ReducedMedium> m_rmedia;
    fluo_detail::FluoWrappers<Float, Spectrum> m_wrappers;
    std::unordered_map<const void *, MediumEntry> m_media;
};

static const bool fluo_volpath_registered =
    (fluo_detail::register_scalar_plugin<FluoVolpath>("fluo_volpath", ObjectType::Integrator), true);

NAMESPACE_END(mitsuba)
