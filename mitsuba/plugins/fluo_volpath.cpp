// fluo_volpath, one class template for every variant it serves: Mitsuba's volpath loop
// (dr::while_loop; one kernel in the llvm/cuda variants) with fluorescence (the
// documentation below has the estimators): in spectral variants fluorescent media
// (fluo_qd_medium, fluo_dye_medium through fluo_medium.h) re-emit at real collisions and
// fluorescent BSDFs shift at surfaces as in fluo_path; in RGB variants the path carries
// fluo_path's reduced transport (fluo_reduced.h), on which fluorescent media act through
// their reduced operators. Without fluorescence the render is Mitsuba's own volpath (the
// integrator hands the render to one), in every variant.
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
#include "fluo_bispectral.h"
#include "fluo_reduced.h"
#include "fluo_medium.h"
#include "fluo_path_scene.h"
#include "fluo_integrator.h"

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
   - RGB variants only: transport basis of the reduced transport, ``rgb``, ``xyzu``,
     ``x7`` or ``auto``, as for ``fluo_path`` (whose documentation says which when).
     (Default: ``x7``, unlike ``fluo_path``: on the ``fluo bench`` cuvette of quantum-dot
     media under D65 the mean ΔE00 floor against the spectral reference is 3.47 with
     ``x7`` and 4.96 with ``auto``, where the surface scenes favour ``auto``. D65's light
     band spans the visible range, and light scattered many times in a fluorescent medium
     is the part no basis reduces exactly.)
 * - method
   - |string|
   - RGB variants only: reduction, ``ours`` or ``naive``, as for ``fluo_path``.
     (Default: ``ours``)

Mitsuba's ``volpath`` (delta tracking with null collisions, next-event estimation
through media with ratio-tracked transmittance, MIS between emitter and phase/BSDF
sampling, index-matched ``null`` boundaries, Russian roulette), extended with
fluorescence, in every variant fluo serves (one class and one loop for both transports,
``dr::while_loop`` as Mitsuba's integrators):

* **in media** that implement fluo's bispectral medium interface (``fluo_qd_medium``):
  at an absorption event the medium re-emits isotropically at a longer wavelength;
* **at surfaces**: everything ``fluo_path`` does for fluo's fluorescent BSDFs
  (``fluo_jung``, ``fluo_qd``, ``fluo_matrix``, ``fluo_gmm``, inside ``twosided``,
  ``blendbsdf``, ``mask``, ``normalmap``, ``bumpmap``), with the same code.

**Without fluorescence it is volpath.** At render start the scene is scanned for
fluorescent BSDFs and media (and the emitters' spectral range R, as ``fluo_path`` does;
re-emission by media extends R to the media's emission range). With none left the
render is handed to Mitsuba's own ``volpath`` with the same ``max_depth``, ``rr_depth``
and ``hide_emitters``: identical images, seed for seed. A medium with
``quantum_yield`` 0 is a plain absorbing, scattering medium.

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
medium's reradiation per unit absorbed power). With μf(λo) = ∫_R μa f dλi (from the
medium's tables), each λo independently picks the elastic event with
probability pe = σs/(σs + μf), else a shift, sampling λi ∝ μa(λi) f(λi → λo) (the
medium inverts the CDF of its tabulated μa, linear between nodes, within 3e-7 of μa's
peak for a dye). Both branches then carry the same weight σs + μf in place
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
path's wavelengths are looked up once per flight, not per collision):
optically thick fluorescent media (τ ≫ 100 over the scene) render slowly; fluorescence
itself costs one excitation sample per shifted wavelength at real collisions, and the
paths it continues (re-emitted light goes on where volpath's absorbed light stops).

**Reduced RGB transport (RGB variants).** With fluorescent media or BSDFs in the scene,
the RGB variants carry fluo_path's reduced transport (its ``basis``: K bands; the RGB
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
the same fluorescent-source rule). A shadow ray through fluorescent media multiplies the
vertex's 3×K row block by each null operator it meets (3K² per collision). Native
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

**Variants.** Spectral variants shift wavelengths, RGB variants carry the reduced
transport; the media interpolate Rust's tables of μa and the emission
(``fluo_medium.h``), the fluorescent BSDFs' matrices are fluo_path's
(``fluo_reduced.h``). Gradients (``llvm_ad_*``, ``cuda_ad_*``) reach the
surfaces' differentiable parameters and the media's (``fluo_qd_medium``'s concentration,
``fluo_dye_medium``'s sigma_a, a density, σs, and Mitsuba's own media's) through this loop,
recorded as Mitsuba's default ``render_backward`` does (memory grows with depth; see
``fluo_prbvolpath`` below): tentative collisions are sampled without gradients (on the main
path and on shadow rays) and each event is weighed by its coefficients with gradients at
the detached collision (Mitsuba's ``get_scattering_coefficients``, and ``get_majorant`` for
native media, whose flight then weighs tr(θ) over the detached pdf: a homogeneous medium's
d/dσt came out 0.0089 against 0.208 by differences while collisions moved with σt, as
Mitsuba's ``volpath`` gives 0.019), every probability detached, fluorescent media under a
detached majorant 1.5× the render's (clear of σt, so that every wavelength's null
collisions keep a probability; the derivative pass traces more tentative collisions than
the render). Where nothing fluoresces the primal render is ``volpath``'s and the
derivatives are still this loop's.

**Path replay (``fluo_prbvolpath``).** The same class registered as ``fluo_prbvolpath``
renders exactly what ``fluo_volpath`` renders and, in the AD variants (``llvm_ad_*``,
``cuda_ad_*``), replays each path for reverse-mode derivatives instead of recording the
loop (Vicini et al. 2021, as Mitsuba's ``prbvolpath``; fluo_prb's three passes, ``fluo_path_scene.h``): the same paths again
(same collisions, null/real choices, shifts and wavelengths) carrying the radiance still
to come, each event backpropagating δL times its emission, its next-event estimate and the
rest of the path through the relative derivative of its weights (free flight, σn or the
real collision's σs + μf, the shift's excitation density, phase function, BSDF) at once:
memory independent of depth. A next-event estimate's transmittance is tracked a second
time with the same random numbers (a clone of the sampler) to backpropagate each ratio
tracking step's factor. With roulette off its derivatives equal the recorded loop's to
5e-6 (test_fluo_prbvolpath.py). In the RGB variants (the reduced transport) each event's
radiance still to come is the path's rest per unit of matrix throughput: K coefficients
from continuations carrying the identity's rows (⌈K/3⌉ per event, as ``fluo_prb``'s;
memory independent of depth, time growing with its square), and a next-event estimate's
T·c(light) likewise from continuations of its shadow ray. A shadow ray's own factors
(a medium's coefficients, a null surface's transmission) are differentiated at each
tracking step that carries derivatives: its value is linear in the RGB transmittance so
far and in the 3×K operator so far, so the step's derivative needs the rest of the ray
per unit of each, from 3 + ⌈K/3⌉ continuations of the ray (time growing with the square of
its steps, only where a medium's or null surface's parameter has gradients). The
polarized variants refuse it.

Mitsuba's ``volpath`` renders fluorescent media as absorbing only (their Q = 0 limit)
and warns once per scene.

.. tabs::
    .. code-tab:: xml

        <integrator type="fluo_volpath">
            <integer name="max_depth" value="16"/>
        </integrator>

        <!-- reverse-mode gradients with memory independent of path depth (spectral) -->
        <integrator type="fluo_prbvolpath">
            <integer name="max_depth" value="16"/>
        </integrator>
*/

template <typename Float, typename Spectrum>
class FluoVolpath final : public FluoIntegrator<Float, Spectrum> {
public:
    MI_IMPORT_BASE(FluoIntegrator, m_max_depth, m_rr_depth, m_hide_emitters, m_lambda_min, m_reduced, m_bsdfs,
                   m_range_lo, m_range_hi, m_wrappers, m_directional, m_varying, m_differentiating, m_replayer)
    MI_IMPORT_TYPES(Scene, Sensor, Sampler, Medium, MediumPtr, Emitter, EmitterPtr, BSDF, BSDFPtr, Shape,
                    PhaseFunctionContext, PhaseFunction, PhaseFunctionPtr)
    using typename Base::Bispectral;
    using typename Base::Reduced;
    using typename Base::Wrappers;
    using typename Base::WMask;
    using BMedium = fluo_detail::BispectralMedium<Float, Spectrum>;
    template <size_t K> using Coeffs = typename Base::template Coeffs<K>;
    template <size_t K> using Rows = typename Base::template Rows<K>;

    static constexpr const char *Plugin = "fluo_volpath";
    static constexpr float InvFourPi = fluo_detail::InvFourPi;

    FluoVolpath(const Properties &props) : Base(props, Plugin, "fluo_prbvolpath", "x7") {
        Properties vp("volpath");
        vp.set("max_depth", (int64_t) props.get<int64_t>("max_depth", -1));
        vp.set("rr_depth", (int64_t) props.get<int64_t>("rr_depth", 5));
        vp.set("hide_emitters", props.get<bool>("hide_emitters", false));
        m_volpath = PluginManager::instance()->create_object<MonteCarloIntegrator<Float, Spectrum>>(vp);
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
            << "  basis = " << m_reduced.name() << " (RGB variants)" << std::endl
            << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(FluoVolpath)

protected:
    /// Once per render: the fluorescent media and BSDFs (and the wrappers around those) and
    /// the emitters' spectral range; whether anything fluoresces. RGB variants: the reduced
    /// transport's matrices (the BSDFs' and the media's operators) and the emitters' basis
    /// coefficients.
    void prepare(Scene *scene) override {
        m_media.clear();
        m_media_set.clear();
        m_bsdfs.clear();
        m_rmedia.clear();
        std::vector<const BMedium *> media = fluo_detail::managed_media<BMedium>(scene);
        double reemitted = 0.0;
        for (const BMedium *b : media)
            if (b->jit_fluorescent(0.0, 1e30))
                reemitted = std::max(reemitted, b->jit_range().hi);
        std::vector<Bispectral *> bsdfs = this->scan(scene, reemitted);
        const double lo = m_range_lo, hi = m_range_hi;
        for (const BMedium *b : media)
            fluo_detail::rust_call(Plugin, [&] { b->jit_prepare(lo, hi); }); // the parameters carrying gradients
        if (!scene->emitters().empty())
            for (const BMedium *b : media)
                if (b->jit_fluorescent(lo, hi))
                    m_media.push_back(b);
        m_bsdfs.assign(bsdfs);
        m_media_set.assign(m_media);
        m_fluorescent = !m_media.empty() || !m_bsdfs.empty();
        if constexpr (is_rgb_v<Spectrum>) {
            m_reduced.prepare(scene, bsdfs, !m_media.empty());
            m_varying = m_directional && m_reduced.varying();
            size_t k = m_reduced.bands();
            for (const BMedium *b : m_media) {
                ReducedMedium r{ dynamic_cast<const Medium *>(b), std::vector<double>(k * k),
                                 std::vector<double>(k * k), std::vector<double>(k, 0.0), { 0.0 }, { 0.0 } };
                fluo_detail::rust_call(Plugin, [&] {
                    b->jit_reduced_operators(m_reduced.basis(), rust::Slice<double>(r.a.data(), k * k),
                                             rust::Slice<double>(r.f.data(), k * k));
                });
                for (size_t i = 0; i < k; ++i) {
                    for (size_t j = 0; j < k; ++j)
                        r.f_rows[i] += std::abs(r.f[i * k + j]) * InvFourPi;
                    r.f_max[0] = std::max(r.f_max[0], r.f_rows[i]);
                    r.a_max[0] = std::max(r.a_max[0], r.a[i * k + i]);
                }
                // the operators with the derivatives of the medium's parameters carrying gradients
                for (auto &t : fluo_detail::rust_call(Plugin, [&] { return b->jit_reduced_tangents(m_reduced.basis()); })) {
                    r.a_t.emplace_back(t.delta, std::move(t.a));
                    r.f_t.emplace_back(t.delta, std::move(t.f));
                }
                m_rmedia.push_back(std::move(r));
            }
        }
    }

    /// trace() with the carried throughput: the reduced transport's K bands in RGB variants.
    std::pair<Spectrum, Bool> trace_sample(const Scene *scene, Sampler *sampler, const RayDifferential3f &ray,
                                           const Medium *medium, Float * /* aovs */, Bool active, bool adjoint,
                                           bool clip) const override {
        return this->with_bands(true, [&](auto k) {
            return trace<decltype(k)::value>(scene, sampler, ray, medium, active, adjoint, clip);
        });
    }
    /// RGB variants clip per sample (trace<K>).
    bool clipped() const override { return !is_spectral_v<Spectrum>; }
    /// volpath renders a scene where nothing fluoresces, except in a derivative pass: those
    /// always run this loop, since volpath's tracking draws null or real with the attached
    /// σn/μ̄, whose derivative is not the integrand's (a pure absorber's d/dc came out +0.04
    /// against −2.4 by differences).
    MonteCarloIntegrator<Float, Spectrum> *delegate() const override {
        auto *volpath = const_cast<MonteCarloIntegrator<Float, Spectrum> *>(m_volpath.get());
        return m_fluorescent || m_differentiating ? nullptr : volpath;
    }

private:
    /// A fluorescent medium's majorant in a derivative pass (render_forward/backward), over
    /// the render's: clear of σt, so that every wavelength's null rate, 0 in value where the
    /// most absorbing one sets the majorant, keeps a probability (a path whose only live
    /// wavelength was that one drew real collisions alone and lost its transmittance's
    /// derivative: a dye's glow came out too steep, AD −3.51e-4 against −3.75e-4).
    static constexpr float DerivativeMargin = 1.5f;

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
            [lo, hi, this](const Medium *m, const Wavelength &lambda_, const Mask &on) {
                const BMedium *f = m_media_set.find(m);
                return f ? f->jit_rates(lambda_, lo, hi, on)
                         : std::make_pair(UnpolarizedSpectrum(0.f), UnpolarizedSpectrum(0.f));
            },
            lambda, active);
    }

    /// A tentative collision: fluorescent media through jit_sample_interaction with the
    /// flight's rates (their majorant covering the source up to `rate`), the others through
    /// Mitsuba's sample_interaction with the path's distance-sampling `channel` (as volpath).
    /// Returns it, μf there (0 for the others), where it is fluorescent and the factor d
    /// (density·scale: 1/m at density 1 to inverse scene units).
    std::tuple<MediumInteraction3f, UnpolarizedSpectrum, Mask, Float>
    sample_medium(const MediumPtr &medium, const Ray3f &ray, const Float &u, const UInt32 &channel,
                  const Float &rate, const UnpolarizedSpectrum &mu_a, const UnpolarizedSpectrum &mu_f,
                  const Mask &active) const {
        const float margin = m_differentiating ? DerivativeMargin : 1.f;
        return fluo_detail::dispatch_any(
            medium,
            [this, margin](const Medium *m, const Ray3f &ray_, const Float &u_, const UInt32 &channel_,
                           const Float &rate_, const UnpolarizedSpectrum &mu_a_, const UnpolarizedSpectrum &mu_f_,
                           const Mask &on) {
                if (const BMedium *f = m_media_set.find(m)) {
                    auto [mei, mf, d] = f->jit_sample_interaction(ray_, u_, rate_, mu_a_, mu_f_, margin, on);
                    return std::make_tuple(mei, mf, Mask(true), d);
                }
                return std::make_tuple(m->sample_interaction(ray_, u_, channel_, on), UnpolarizedSpectrum(0.f),
                                       Mask(false), Float(0.f));
            },
            ray, u, channel, rate, mu_a, mu_f, active);
    }

    /// Channel `c` of a per-channel value (volpath's distance-sampling channel: random per
    /// path in RGB variants, 0 in spectral ones, where the hero wavelength samples distances).
    static Float channel_of(const UnpolarizedSpectrum &v, const UInt32 &c) {
        if constexpr (is_rgb_v<Spectrum>)
            return dr::select(c == 0u, v[0], dr::select(c == 1u, v[1], v[2]));
        else
            return (void) c, v[0];
    }

    /// Null and real collision probabilities in a fluorescent medium: spectral tracking
    /// with the fluorescent source's floor on p_real (collision_probabilities; the docs'
    /// estimator).
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
        return collision_probabilities(q_null, q_real, kappa, mei.combined_extinction[0]);
    }

    /// (p_null, p_real) from the tracking weights q_null, q_real and the source rate κ
    /// (p_real at least min(κ/μ̄, 1/2)).
    static std::pair<Float, Float> collision_probabilities(const Float &q_null, const Float &q_real,
                                                           const Float &kappa, const Float &majorant) {
        Float total = q_null + q_real;
        Mask ok = total > 0.f && dr::isfinite(total);
        Float p_real = dr::select(ok, q_real / total, 1.f);
        p_real = dr::select(ok && majorant > 0.f && dr::isfinite(majorant),
                            dr::maximum(p_real, dr::minimum(kappa / majorant, .5f)), p_real);
        p_real = dr::clip(p_real, 0.f, 1.f);
        return { 1.f - p_real, p_real };
    }

    /// At a surface the path reached (`intersect`: by a new ray): hidden area emitters on the
    /// camera ray skipped (hide_emitters), then the emission found there with
    /// its MIS weight (volpath's): the emitter, its radiance, the weight and where it counts.
    template <typename State>
    std::tuple<EmitterPtr, Spectrum, Float, Mask> surface_emission(const Scene *scene, State &ls,
                                                                   const Mask &active_surface,
                                                                   const Mask &intersect) const {
        if (m_hide_emitters) {
            Mask skip = intersect && ls.depth == 0u && ls.si.is_valid() && ls.si.shape->emitter() != nullptr;
            if (dr::any_or<true>(skip)) {
                Ray3f skip_ray = ls.si.spawn_ray(ls.ray.d);
                PreliminaryIntersection3f pi = Base::skip_area_emitters(scene, skip_ray, true, skip);
                dr::masked(ls.si, skip) = pi.compute_surface_interaction(skip_ray, +RayFlags::All, skip);
            }
        }
        Mask count_direct = ls.depth == 0u || ls.specular_chain;
        EmitterPtr emitter = ls.si.emitter(scene);
        Mask active_e = active_surface && emitter != nullptr && !(ls.depth == 0u && m_hide_emitters);
        Float weight = 1.f;
        Spectrum emitted = 0.f;
        if (dr::any_or<true>(active_e)) {
            Float emitter_pdf = 1.f;
            Mask mis_e = active_e && !count_direct;
            if (dr::any_or<true>(mis_e)) {
                DirectionSample3f ds(scene, ls.si, ls.last_scatter_event);
                dr::masked(emitter_pdf, mis_e) = scene->pdf_emitter_direction(ls.last_scatter_event, ds, mis_e);
            }
            emitted = emitter->eval(ls.si, active_e);
            weight = dr::select(count_direct, 1.f, fluo_detail::mis_weight(ls.last_scatter_direction_pdf, emitter_pdf));
        }
        return { emitter, emitted, weight, active_e };
    }

    /// Where the path reaches a surface (`active`, or an escaped medium flight): its
    /// intersection when the ray is new. Returns where it was intersected here.
    template <typename State> Mask reach_surface(const Scene *scene, State &ls, const Mask &active) const {
        Mask intersect = active && ls.needs_intersection;
        if (dr::any_or<true>(intersect))
            dr::masked(ls.si, intersect) = scene->ray_intersect(ls.ray, intersect);
        ls.needs_intersection &= !intersect;
        return intersect;
    }

    /// A new flight in a fluorescent medium (where `active` and the ray is new): its length to
    /// the next surface first (the source rate of its tentative collisions is at most 1/ℓ).
    /// Returns where a flight starts; the caller looks up its rates there.
    template <typename State> Mask start_flight(const Scene *scene, State &ls, const Mask &active) const {
        Mask flight = ls.needs_intersection && is_fluorescent_medium(ls.medium, active);
        if (dr::any_or<true>(flight)) {
            dr::masked(ls.si, flight) = scene->ray_intersect(ls.ray, flight);
            dr::masked(ls.inv_len, flight) = dr::select(ls.si.is_valid(), dr::rcp(dr::maximum(ls.si.t, 1e-30f)), 0.f);
            ls.needs_intersection &= !flight;
        }
        return flight;
    }

    /// A tentative collision `mei` sampled where `active`: kept, the ray clipped at it in
    /// homogeneous media (as volpath), the surface ahead found, and a collision beyond it
    /// dropped.
    template <typename State>
    void place_collision(const Scene *scene, State &ls, const MediumInteraction3f &mei, const Mask &active) const {
        dr::masked(ls.mei, active) = mei;
        dr::masked(ls.ray.maxt, active && ls.medium->is_homogeneous() && ls.mei.is_valid()) = ls.mei.t;
        Mask intersect = ls.needs_intersection && active;
        if (dr::any_or<true>(intersect))
            dr::masked(ls.si, intersect) = scene->ray_intersect(ls.ray, intersect);
        ls.needs_intersection &= !active;
        dr::masked(ls.mei.t, active && ls.si.t < ls.mei.t) = dr::Infinity<Float>;
    }

    /// A tentative collision placed (place_collision): the free flight's weight tr/pdf where the
    /// medium's extinction is spectral (native media; volpath's, applied by the caller where
    /// is_spectral held on entry, escaping flights included), the masks following the flight
    /// (`escaped` where it left the medium), and volpath's null and real probabilities (the mean
    /// over the channels).
    template <typename State>
    std::tuple<UnpolarizedSpectrum, Float, Float> end_flight(const State &ls, Mask &active_medium, Mask &escaped,
                                                             Mask &is_spectral, Mask &not_spectral,
                                                             Mask &is_fluo) const {
        UnpolarizedSpectrum w(1.f);
        if (dr::any_or<true>(is_spectral)) {
            auto [tr, free_flight_pdf] = ls.medium->transmittance_eval_pdf(ls.mei, ls.si, is_spectral);
            Float tr_pdf = channel_of(free_flight_pdf, ls.channel);
            w = dr::select(tr_pdf > 0.f, tr / tr_pdf, 0.f);
        }
        escaped = active_medium && !ls.mei.is_valid();
        active_medium &= ls.mei.is_valid();
        is_spectral &= active_medium;
        not_spectral &= active_medium;
        is_fluo &= active_medium;
        return { w, dr::mean(ls.mei.sigma_n / ls.mei.combined_extinction),
                 dr::mean(ls.mei.sigma_t / ls.mei.combined_extinction) };
    }

    /// Russian roulette on the throughput's largest entry `t_max` and max_depth (as volpath;
    /// `alive`: where the throughput is not all 0): ends the paths that stop; returns where the
    /// survivors' throughput must be scaled, and by what.
    template <typename State>
    std::pair<Mask, Float> roulette(State &ls, const Float &t_max, const Mask &alive) const {
        ls.active &= alive;
        Float q = dr::minimum(t_max * dr::square(ls.eta), .95f);
        Mask perform_rr = ls.depth > (uint32_t) m_rr_depth;
        ls.active &= ls.sampler->next_1d(ls.active) < q || !perform_rr;
        ls.active &= ls.depth < (uint32_t) m_max_depth;
        return { perform_rr, dr::rcp(dr::detach(q)) };
    }

    /// After the null/real choice: a real collision (`scatter`) counts towards the depth and
    /// is the last scattering event (as volpath), paths at max_depth stop, and a null one
    /// moves the ray's origin to it.
    template <typename State> void settle_collision(State &ls, const Mask &null, Mask &scatter) const {
        dr::masked(ls.depth, scatter) += 1;
        dr::masked(ls.last_scatter_event, scatter) = Interaction3f(ls.mei);
        ls.active &= ls.depth < (uint32_t) m_max_depth;
        scatter &= ls.active;
        dr::masked(ls.ray.o, null) = ls.mei.p;
        dr::masked(ls.si.t, null) = ls.si.t - ls.mei.t;
    }

    /// A real collision where `scatter`: valid ray, specular chain (as volpath); returns the
    /// medium's phase function (nullptr elsewhere) and where emitters are sampled.
    template <typename State> std::pair<PhaseFunctionPtr, Mask> begin_scatter(State &ls, const Mask &scatter) const {
        PhaseFunctionPtr phase = ls.mei.medium->phase_function();
        dr::masked(phase, !scatter) = nullptr;
        Mask sample_emitters = ls.mei.medium->use_emitter_sampling();
        ls.valid_ray |= scatter;
        ls.specular_chain &= !scatter;
        ls.specular_chain |= scatter && !sample_emitters;
        return { phase, scatter && sample_emitters };
    }

    /// After a BSDF sample `bs` at si where `active`: the next ray (carrying the path's
    /// wavelengths), η, the depth and the previous vertex for MIS, the specular chain and the
    /// medium behind a transition (as volpath).
    template <typename State>
    void leave_surface(State &ls, const SurfaceInteraction3f &si, const BSDFSample3f &bs, const Mask &active) const {
        dr::masked(ls.eta, active) *= bs.eta;
        dr::masked(ls.ray, active) = si.spawn_ray(si.to_world(bs.wo));
        ls.needs_intersection |= active;
        Mask non_null = active && !has_flag(bs.sampled_type, BSDFFlags::Null);
        dr::masked(ls.depth, non_null) += 1;
        dr::masked(ls.last_scatter_event, non_null) = Interaction3f(si);
        dr::masked(ls.last_scatter_direction_pdf, non_null) = bs.pdf;
        ls.valid_ray |= non_null;
        ls.specular_chain |= non_null && has_flag(bs.sampled_type, BSDFFlags::Delta);
        ls.specular_chain &= !(active && has_flag(bs.sampled_type, BSDFFlags::Smooth));
        Mask transition = active && si.is_medium_transition();
        dr::masked(ls.medium, transition) = si.target_medium(ls.ray.d);
    }

    /// What a path carries. K = 0 (spectral variants): Mitsuba's throughput, shifted in
    /// wavelength at fluorescent events, and μf of a fluorescent medium at the flight's
    /// wavelengths (density 1). K > 0 (RGB, the reduced transport): the RGB throughput t
    /// until the first fluorescent event, then the 3×K matrix throughput R.
    struct Throughput {
        Spectrum throughput;
        UnpolarizedSpectrum mu_f;
        DRJIT_STRUCT(Throughput, throughput, mu_f)
    };
    template <size_t K> using Carried = typename Base::template Carried<K, Throughput>;

    template <size_t K> struct LoopState {
        Mask active;
        UInt32 depth;
        Ray3f ray;
        Carried<K> c;
        Spectrum result;
        SurfaceInteraction3f si;
        MediumInteraction3f mei;
        MediumPtr medium;
        Float eta;
        Interaction3f last_scatter_event;
        Float last_scatter_direction_pdf;
        Mask needs_intersection, specular_chain, valid_ray;
        Float inv_len; ///< 1/ℓ of the current straight flight (0: no surface ahead)
        /// μa of a fluorescent medium at the flight's wavelengths (density 1; K > 0: its bound)
        UnpolarizedSpectrum mu_a;
        UInt32 channel; ///< volpath's distance-sampling channel (0: spectral variants)
        Sampler *sampler;
        DRJIT_STRUCT(LoopState, active, depth, ray, c, result, si, mei, medium, eta, last_scatter_event,
                     last_scatter_direction_pdf, needs_intersection, specular_chain, valid_ray, inv_len, mu_a, channel,
                     sampler)
    };

    /// A wavelength-preserving weight w where `m`: the throughput times w; K > 0: t·w before
    /// the first fluorescent event, R·diag(band albedos of w) after it.
    template <size_t K, typename Weight> void weigh(Carried<K> &c, const Weight &w, const Mask &m) const {
        if constexpr (K == 0) {
            dr::masked(c.throughput, m) *= w;
        } else {
            Rows<K> scaled = Reduced::template scale_columns<K>(c.R, m_reduced.template band_albedo<K>(Color3f(w)));
            c.R = dr::select(m && c.reduced, scaled, c.R);
            dr::masked(c.t, m && !c.reduced) *= Color3f(w);
        }
    }

    /// What the iterations of one trace() share: whether it is fluo_prbvolpath's replay
    /// (`adjoint`, with the sample's adjoint radiance δL) or a derivative pass
    /// (`differentiating`), and the render's flags.
    struct Walk {
        bool adjoint = false, differentiating = false, directional = false, surfaces = false, media = false;
        double range_lo = 0.0, range_hi = 0.0;
        Spectrum delta_L;
    };

    /// volpath's loop with fluorescence; what differs between the carried throughputs is
    /// marked K == 0 (wavelength shifting) / K > 0 (the reduced transport). `adjoint`:
    /// fluo_prbvolpath's replay; K = 0: `result` holds the radiance still to come (the
    /// primal's, less what the events passed gave); K > 0: each iteration's radiance still to
    /// come is estimated by future(). `clip`: K > 0 clips out-of-gamut colours per sample
    /// (the replay's primal pass keeps them: their sign masks δL).
    template <size_t K>
    std::pair<Spectrum, Bool> trace(const Scene *scene, Sampler *sampler, const RayDifferential3f &ray_,
                                    const Medium *initial_medium, Bool active, bool adjoint = false,
                                    bool clip = true) const {
        // volpath's distance-sampling channel: one per path in RGB variants
        UInt32 channel(0);
        if constexpr (is_rgb_v<Spectrum>)
            channel = UInt32(dr::minimum(sampler->next_1d(active) * 3.f, 2.f));
        Carried<K> start;
        if constexpr (K == 0)
            start = { Spectrum(1.f), UnpolarizedSpectrum(0.f) };
        else
            start = { Color3f(1.f), dr::zeros<Rows<K>>(), Mask(false) };
        LoopState<K> ls = { active, UInt32(0), Ray3f(ray_), start, Spectrum(0.f), dr::zeros<SurfaceInteraction3f>(),
                            dr::zeros<MediumInteraction3f>(), MediumPtr(initial_medium), Float(1.f),
                            dr::zeros<Interaction3f>(), Float(1.f), Mask(true), Mask(active && !m_hide_emitters),
                            Mask(!m_hide_emitters && scene->environment() != nullptr), Float(0.f),
                            UnpolarizedSpectrum(0.f), channel, sampler };
        adjoint &= dr::is_diff_v<Float>;
        // a derivative pass: media sampled without gradients, their coefficients with them at
        // the detached collisions (attach_collision; as volpath, d/dσt of a homogeneous medium
        // came out 0.0089 and 0.0096 against 0.208 by differences, spectral and RGB)
        Walk w{ adjoint, m_differentiating || adjoint, m_directional, K == 0 ? !m_bsdfs.empty() : m_reduced.size() > 0,
                !m_media.empty(), m_range_lo, m_range_hi, Spectrum() };
        if constexpr (dr::is_diff_v<Float>) {
            if (adjoint) {
                if constexpr (K == 0)
                    ls.result = m_replayer.primal();
                w.delta_L = m_replayer.adjoint();
            }
        }
        this->loop(ls, [&](LoopState<K> &s) { step<K>(scene, s, w); });
        if constexpr (K == 0)
            return { ls.result, ls.valid_ray };
        else if (clip) // out-of-gamut colours are clipped per sample (as fluo_path does)
            return { dr::select(ls.valid_ray, dr::maximum(ls.result, 0.f), 0.f), ls.valid_ray };
        else
            return { dr::select(ls.valid_ray, ls.result, 0.f), ls.valid_ray };
    }

    /// One iteration of trace()'s loop: a free flight and its collision, or a surface.
    template <size_t K> void step(const Scene *scene, LoopState<K> &ls, const Walk &w) const {
        const bool adjoint = w.adjoint, differentiating = w.differentiating, directional = w.directional,
                   surfaces = w.surfaces, media = w.media;
        const double range_lo = w.range_lo, range_hi = w.range_hi;
        const Spectrum &delta_L = w.delta_L;
        constexpr size_t KC = K == 0 ? 1 : K; // (the band arrays' size where K = 0 has none)
        Mask &active = ls.active;
        Carried<K> &c = ls.c;
        Sampler *sampler = ls.sampler;
        // The replay: this iteration's values with gradients, what it gives (Lo)
        // backpropagated at its end, sampling without gradients (as prbvolpath); the
        // throughput enters detached, so the rest of the path's derivative is, after the
        // iteration's weights, result·relative(throughput) (K = 0) or R·future() (K > 0).
        dr::resume_grad<Float> attached(adjoint);
        Spectrum Lo = 0.f;
        auto detached = [adjoint](auto &&f) {
            dr::suspend_grad<Float> off(adjoint);
            return f();
        };
        auto detached_media = [differentiating](auto &&f) {
            dr::suspend_grad<Float> off(differentiating);
            return f();
        };
        // (the replay's first tracking renders; its second, in shadow(), replays)
        const Shadow shadow_mode = differentiating && !adjoint ? Shadow::Recorded : Shadow::Render;
        auto add = [&](const Spectrum &x, const Mask &m) { // a contribution to the radiance
            if (adjoint) {
                Spectrum v = dr::select(m, x, 0.f);
                Lo += v;
                if constexpr (K == 0) // (K > 0: the radiance still to come is future()'s)
                    ls.result -= dr::detach(v);
            } else {
                dr::masked(ls.result, m) += x;
            }
        };
        // K = 0: a next-event estimate's transmittance, the replay keeping a clone of the
        // sampler to track it again with gradients
        auto transmittance = [&](const auto &at, const DirectionSample3f &ds, ref<Sampler> &again,
                                 const Mask &on) {
            if (dr::none_or<false>(on))
                return Spectrum(1.f);
            if (adjoint)
                again = sampler->clone();
            return detached([&] {
                return std::get<0>(
                    transmit<0>(at, ds, scene, sampler, ls.medium, ls.channel, Float(0.f), on, shadow_mode));
            });
        };
        // ... and its contribution x, whose transmittance's derivative the replay
        // backpropagates along the same ratio tracking
        auto shadow = [&](const auto &at, const DirectionSample3f &ds, ref<Sampler> &again,
                          const Spectrum &x, const Mask &on) {
            add(x, on);
            if constexpr (K == 0)
                if (adjoint && dr::any_or<true>(on))
                    transmit<0>(at, ds, scene, again.get(), ls.medium, ls.channel, Float(0.f), on,
                                Shadow::Replay, delta_L * dr::detach(dr::select(on, x, 0.f)));
        };

        // ----------------- Russian roulette, max_depth -----------------
        if constexpr (K == 0) {
            auto [perform_rr, rr] = roulette(ls, dr::max(unpolarized_spectrum(c.throughput)),
                                             dr::any(unpolarized_spectrum(c.throughput) != 0.f));
            dr::masked(c.throughput, perform_rr) *= rr;
        } else {
            Float t_max = dr::select(c.reduced, Reduced::template max_abs<K>(c.R), dr::max(c.t));
            auto [perform_rr, rr] = roulette(ls, t_max, t_max != 0.f);
            dr::masked(c.t, perform_rr) *= rr;
            dr::masked(c.R, perform_rr) *= rr;
        }
        if (dr::none_or<false>(active))
            return;

        // ------------------------ Sampling the RTE ---------------------
        Mask active_medium = active && ls.medium != nullptr;
        Mask active_surface = active && !active_medium;
        Mask act_null = false, act_scatter = false, escaped = false;
        Mask is_spectral = active_medium, not_spectral = false, is_fluo = false;
        Float p_null = 0.f, p_real = 1.f, d = 0.f;
        UnpolarizedSpectrum mu_f = 0.f;                   // K = 0: μf at the collision
        Coeffs<KC> sigma_s = dr::zeros<Coeffs<KC>>();     // K > 0: a fluorescent collision's σs per band
        MediaMasks which;
        if (dr::any_or<true>(active_medium)) {
            is_spectral &= ls.medium->has_spectral_extinction();
            not_spectral = !is_spectral && active_medium;
            Mask fluo_flight = detached_media([&] { return start_flight(scene, ls, active_medium); });
            // what the majorant covers of the source rate (up to 1/ℓ)
            UnpolarizedSpectrum source = 0.f;
            if constexpr (K == 0) {
                if (dr::any_or<true>(fluo_flight)) {
                    auto [mu_a, mu_f_] =
                        detached_media([&] { return rates(ls.medium, ls.ray.wavelengths, fluo_flight); });
                    dr::masked(ls.mu_a, fluo_flight) = mu_a;
                    dr::masked(c.mu_f, fluo_flight) = mu_f_;
                }
                source = c.mu_f;
            } else {
                if (dr::any_or<true>(fluo_flight))
                    dr::masked(ls.mu_a, fluo_flight) =
                        absorption_bound<K>(ls.medium, ls.ray.wavelengths, fluo_flight);
                if (media)
                    which = which_media(ls.medium);
                source = media ? per_medium(which, &ReducedMedium::f_max, 0) : Float(0.f);
            }
            Float rate = dr::select(ls.inv_len > 0.f, ls.inv_len, dr::Infinity<Float>);
            auto [mei, mf, fl, dd] = detached_media([&] {
                return sample_medium(ls.medium, ls.ray, sampler->next_1d(active_medium), ls.channel, rate,
                                     ls.mu_a, source, active_medium);
            });
            detached_media([&] { return place_collision(scene, ls, mei, active_medium); });
            mu_f = mf;
            d = dd;
            is_fluo = fl && active_medium;
            if constexpr (K > 0)
                is_spectral &= !is_fluo; // R carries a fluorescent medium's weights
            Mask weighted = is_spectral; // (escaping flights too)
            auto [w, pn, pr] = end_flight(ls, active_medium, escaped, is_spectral, not_spectral, is_fluo);
            if (differentiating) // the collision's coefficients (and the flight's weight) with gradients
                attach_collision(ls, w, mu_f, d, weighted, is_fluo, active_medium);
            weigh<K>(c, w, weighted);

            // Null or real: volpath's rule; in fluorescent media spectral tracking
            // (K = 0) or band tracking on R (K > 0). The probabilities are detached:
            // a weight σ/p then differentiates σ alone (the choice's own derivative
            // is not the integrand's).
            p_null = dr::detach(pn);
            p_real = dr::detach(pr);
            Float majorant = ls.mei.combined_extinction[0];
            if (media && dr::any_or<true>(is_fluo)) {
                std::pair<Float, Float> p;
                if constexpr (K == 0) {
                    p = spectral_tracking(ls.mei, c.throughput, mu_f, ls.inv_len);
                } else {
                    c.R = dr::select(is_fluo && !c.reduced, m_reduced.template output_rows<K>(c.t), c.R);
                    c.reduced |= is_fluo;
                    sigma_s = m_reduced.template band_albedo<K>(ls.mei.sigma_s);
                    p = band_tracking<K>(c.R, sigma_s, d, majorant, ls.inv_len, which);
                }
                p_null = dr::select(is_fluo, dr::detach(p.first), p_null);
                p_real = dr::select(is_fluo, dr::detach(p.second), p_real);
            }
            Mask null_scatter = sampler->next_1d(active_medium) < p_null;
            act_null = null_scatter && active_medium;
            act_scatter = !null_scatter && active_medium;
            weigh<K>(c, ls.mei.sigma_n / p_null, act_null && is_spectral);
            if constexpr (K > 0) {
                Mask fl_null = act_null && is_fluo;
                if (media && dr::any_or<true>(fl_null)) { // R ← R·(μ̄ − σs − d·A)/(μ̄ p_null)
                    Float s = dr::rcp(majorant * p_null);
                    Coeffs<K> g;
                    for (size_t k = 0; k < K; ++k)
                        g[k] = (majorant - sigma_s[k]) * s;
                    c.R = dr::select(fl_null, medium_product<K>(c.R, g, -d * s, &ReducedMedium::a, which),
                                     c.R);
                }
            }
        }
        settle_collision(ls, act_null, act_scatter);

        if (dr::any_or<true>(act_scatter)) {
            // K = 0: elastic scattering, or per wavelength a shift to λi (the docs'
            // estimator). K > 0: a fluorescent medium's source operator
            // W = diag(σs·p) + d·F/(4π) over μ̄ p_real, applied with the direction.
            Mask fl_scatter = act_scatter && is_fluo;
            WMask shifted = false;
            Float real_scale = dr::rcp(ls.mei.combined_extinction[0] * p_real);
            UnpolarizedSpectrum sigma_w = ls.mei.sigma_s;
            if constexpr (K == 0) {
                if (media && dr::any_or<true>(fl_scatter))
                    shifted = shift_collision(ls, mu_f, sampler, fl_scatter, range_lo, range_hi, sigma_w);
            }
            weigh<K>(c, sigma_w / p_real, act_scatter && is_spectral);
            weigh<K>(c, ls.mei.sigma_s / ls.mei.sigma_t, act_scatter && not_spectral);
            if constexpr (K == 0) {
                // A collision that absorbed every wavelength for good ends the path.
                Mask dead = fl_scatter && dr::all(unpolarized_spectrum(c.throughput) == 0.f);
                active &= !dead;
                act_scatter &= !dead;
            }

            PhaseFunctionContext phase_ctx(sampler);
            auto [phase, active_e] = begin_scatter(ls, act_scatter);

            // ------------------------ Emitter sampling -----------------
            if (dr::any_or<true>(active_e)) {
                auto [ds, emitter_val] = detached([&] {
                    return scene->sample_emitter_direction(ls.mei, sampler->next_2d(active_e), false, active_e);
                });
                active_e &= ds.pdf != 0.f;
                if (adjoint) // the emitter's value with gradients at the detached sample
                    emitter_val = fluo_detail::emitter_weight(scene, ls.mei, ds, emitter_val, active_e);
                auto [phase_val, phase_pdf] = phase->eval_pdf(phase_ctx, ls.mei, ds.d, active_e);
                Float mis = fluo_detail::mis_weight(ds.pdf, dr::select(ds.delta, 0.f, phase_pdf));
                if constexpr (K == 0) {
                    // shifted wavelengths re-emit isotropically
                    phase_val =
                        fluo_detail::select_unpolarized(shifted, UnpolarizedSpectrum(InvFourPi), phase_val);
                    ref<Sampler> again;
                    Spectrum emitted = emitter_val * transmittance(ls.mei, ds, again, active_e);
                    shadow(ls.mei, ds, again, c.throughput * phase_val * emitted * mis, active_e);
                } else {
                    Color3f pv(phase_val);
                    Rows<K> Rm = dr::select(c.reduced, c.R, m_reduced.template output_rows<K>(c.t));
                    Rows<K> B = Reduced::template scale_columns<K>(Rm, m_reduced.template band_albedo<K>(pv));
                    if (media && dr::any_or<true>(fl_scatter))
                        B = dr::select(fl_scatter,
                                       source_product<K>(c.R, sigma_s, pv, d, InvFourPi, real_scale, which), B);
                    Color3f adj; // the replay: what the shadow ray's own factors are weighed by
                    if (adjoint)
                        adj = dr::select(active_e, delta_L * dr::detach(mis), 0.f);
                    add(light<K>(ls.mei, ds, emitter_val, scene, sampler, ls.medium, ls.channel, B, c.t * pv,
                                 c.reduced, active_e, shadow_mode, adjoint ? &adj : nullptr) * mis,
                        active_e);
                }
            }

            // ---------------------- Phase function sampling ------------
            if (dr::any_or<true>(act_scatter)) { // (phase is null elsewhere)
                Float phase_1 = sampler->next_1d(act_scatter);
                Point2f phase_2 = sampler->next_2d(act_scatter);
                auto [wo, phase_weight, phase_pdf] = detached_media(
                    [&] { return phase->sample(phase_ctx, ls.mei, phase_1, phase_2, act_scatter); });
                act_scatter &= phase_pdf > 0.f;
                // a derivative pass: the phase function's value with gradients at the detached
                // sample (sampled with them, HG's weight is 1 and d/dg came out 0.0213 against
                // 0.0609 by differences; detached, 0.0607)
                if (differentiating)
                    phase_weight *= fluo_detail::relative(
                        phase->eval_pdf(phase_ctx, ls.mei, wo, act_scatter).first);
                if constexpr (K == 0) {
                    phase_weight = fluo_detail::select_unpolarized(
                        shifted, UnpolarizedSpectrum(InvFourPi / phase_pdf), phase_weight);
                    dr::masked(c.throughput, act_scatter) *= phase_weight;
                } else {
                    fl_scatter &= act_scatter;
                    if (media && dr::any_or<true>(fl_scatter))
                        c.R = dr::select(fl_scatter,
                                         source_product<K>(c.R, sigma_s, Color3f(phase_weight), d,
                                                           InvFourPi / phase_pdf, real_scale, which),
                                         c.R);
                    weigh<K>(c, phase_weight, act_scatter && !is_fluo);
                }
                dr::masked(ls.ray, act_scatter) = ls.mei.spawn_ray(wo); // carries λi where shifted
                ls.needs_intersection |= act_scatter;
                dr::masked(ls.last_scatter_direction_pdf, act_scatter) = phase_pdf;
            }
        }

        // ----------------------- Surface interactions ------------------
        active_surface |= escaped;
        Mask intersect = detached([&] { return reach_surface(scene, ls, active_surface); });

        if (dr::any_or<true>(active_surface)) {
            auto [emitter, emitted, weight, active_e] = surface_emission(scene, ls, active_surface, intersect);
            if (adjoint) // the replay differentiates materials, emitters and media, not geometry
                ls.si = dr::detach(ls.si);
            if constexpr (K == 0)
                add(c.throughput * emitted * weight, active_e);
            else if (dr::any_or<true>(active_e))
                add(m_reduced.template through<K>(c.R, c.t, c.reduced, emitter, emitted, active_e) * weight, active_e);
        }
        active_surface &= ls.si.is_valid();
        if (dr::any_or<true>(active_surface)) {
            BSDFContext ctx;
            SurfaceInteraction3f &si = ls.si;
            BSDFPtr bsdf = si.bsdf(ls.ray);
            typename Wrappers::Perturbations perturbed;
            if (!m_wrappers.empty())
                bsdf = m_wrappers.resolve(bsdf, si, sampler, perturbed, active_surface);
            fluo_detail::SurfaceShift<Float, Spectrum> shift; // K = 0: elastic or shift per wavelength
            if (K == 0 && surfaces)
                shift.choose(m_bsdfs, bsdf, si, sampler, active_surface, range_lo, range_hi);

            // ------------------------ Emitter sampling -----------------
            Mask active_e = active_surface && has_flag(bsdf->flags(), BSDFFlags::Smooth) &&
                            ls.depth + 1 < (uint32_t) m_max_depth;
            DirectionSample3f ds = dr::zeros<DirectionSample3f>();
            Spectrum emitter_val = 0.f;
            ref<Sampler> again; // K = 0, the replay: the shadow ray's numbers again
            if (dr::any_or<true>(active_e)) {
                std::tie(ds, emitter_val) = detached([&] {
                    return scene->sample_emitter_direction(si, sampler->next_2d(active_e), false, active_e);
                });
                active_e &= ds.pdf != 0.f;
                if (adjoint)
                    emitter_val = fluo_detail::emitter_weight(scene, si, ds, emitter_val, active_e);
                if constexpr (K == 0) // (the transmittance before the BSDF's numbers, as volpath)
                    emitter_val *= transmittance(si, ds, again, active_e);
            }
            active_e &= perturbed.keeps_side(ds.d);
            Vector3f wo = si.to_local(ds.d);

            // ---------------- Emitter contribution, BSDF sampling ------
            Float sample_1 = sampler->next_1d(active_surface);
            Point2f sample_2 = sampler->next_2d(active_surface);
            auto [bsdf_val, bsdf_pdf, bs, bsdf_weight] = detached([&] {
                return shift.eval_pdf_sample(m_bsdfs, bsdf, ctx, si, wo, sample_1, sample_2, active_surface);
            });
            if (adjoint) { // the BSDF's values with gradients at the detached samples (as fluo_prb)
                bsdf_val = bsdf->eval(ctx, si, wo, active_e);
                bsdf_weight *= fluo_detail::sampled_relative(bsdf, ctx, si, bs, active_surface);
            } else {
                fluo_detail::detach_moving_sample(bsdf, ctx, si, bs, bsdf_pdf, bsdf_weight, active_surface,
                                                  differentiating);
            }
            Float mis = fluo_detail::mis_weight(ds.pdf, dr::select(ds.delta, 0.f, bsdf_pdf));
            if constexpr (K == 0) {
                if (surfaces)
                    shift.apply(m_bsdfs, bsdf, si, directional, wo, bs, active_surface, bsdf_val, bsdf_weight);
                shadow(si, ds, again, c.throughput * bsdf_val * mis * emitter_val, active_e);
                dr::masked(c.throughput, active_surface) *= bsdf_weight;
            } else {
                Rows<K> Rm = dr::select(c.reduced, c.R, m_reduced.template output_rows<K>(c.t));
                Mask is_fl = false, native_elastic = false;
                Rows<K> B_fl = dr::zeros<Rows<K>>(), R_fl = dr::zeros<Rows<K>>();
                if (surfaces)
                    std::tie(is_fl, native_elastic, B_fl, R_fl) = m_reduced.template vertex<K, true>(
                        bsdf, si, Rm, dr::zeros<Coeffs<K>>(), wo, bs.wo, bs.pdf, m_directional,
                        m_varying ? sampler->next_1d(active_surface) : Float(0.f), active_surface);
                if (dr::any_or<true>(active_e)) {
                    Rows<K> B_red =
                        Reduced::template scale_columns<K>(Rm, m_reduced.template band_albedo<K>(bsdf_val));
                    Rows<K> B = dr::select(is_fl, B_fl + dr::select(native_elastic, B_red, 0.f), B_red);
                    Color3f adj; // the replay: what the shadow ray's own factors are weighed by
                    if (adjoint)
                        adj = dr::select(active_e, delta_L * dr::detach(mis), 0.f);
                    add(light<K>(si, ds, emitter_val, scene, sampler, ls.medium, ls.channel, B, c.t * bsdf_val,
                                 c.reduced || is_fl, active_e, shadow_mode, adjoint ? &adj : nullptr) * mis,
                        active_e);
                }
                m_reduced.template scatter<K>(c.R, c.t, c.reduced, Rm, R_fl, is_fl, native_elastic, bsdf_weight,
                                              active_surface);
            }
            leave_surface(ls, si, bs, active_surface); // the ray carries λi where shifted
            active_surface &= perturbed.keeps_side(ls.ray.d); // a map's sample across the surface
        }
        active &= active_surface || active_medium;
        if constexpr (dr::is_diff_v<Float>) {
            if (adjoint) { // the rest of the path through this iteration's weights
                Carried<K> next = c; // (with this iteration's gradients)
                // the path itself carries no gradients
                c = dr::detach(c);
                ls.si = dr::detach(ls.si);
                ls.mei = dr::detach(ls.mei);
                ls.ray = dr::detach(ls.ray);
                ls.eta = dr::detach(ls.eta);
                ls.last_scatter_event = dr::detach(ls.last_scatter_event);
                ls.last_scatter_direction_pdf = dr::detach(ls.last_scatter_direction_pdf);
                if constexpr (K == 0) {
                    Lo += dr::select(active, ls.result * fluo_detail::relative(next.throughput), 0.f);
                } else { // the matrix throughput after this iteration times what the rest gives
                    auto [coeffs, rgb] = future<K>(scene, ls, w);
                    Lo += dr::select(active, dr::select(c.reduced, Reduced::template apply<K>(next.R, coeffs),
                                                        next.t * rgb),
                                     0.f);
                }
                if (dr::grad_enabled(Lo)) {
                    Spectrum weighted = delta_L * Lo;
                    dr::backward_from(weighted);
                }
            }
        }
    }

    /// K > 0, fluo_prbvolpath's replay: the radiance still to come from `from` per unit of
    /// throughput (fluo_detail::future, this loop's continuations).
    template <size_t K>
    std::pair<Coeffs<K>, Color3f> future(const Scene *scene, const LoopState<K> &from, const Walk &w) const {
        Walk primal = w;
        primal.adjoint = false;
        primal.differentiating = false;
        return fluo_detail::future<K, Coeffs<K>, Color3f>(from, Mask(dr::any(w.delta_L != 0.f)), [&](LoopState<K> &cs) {
            this->loop(cs, [&](LoopState<K> &s) { step<K>(scene, s, primal); });
        });
    }

    /// fluo_prbvolpath's replay: the majorant at a detached collision mei with gradients, as the
    /// replay weighs by it: a native medium's own (get_majorant), a fluorescent one's detached.
    UnpolarizedSpectrum majorant_of(const MediumPtr &medium, const MediumInteraction3f &mei, const Mask &active) const {
        UnpolarizedSpectrum m = dr::detach(mei.combined_extinction);
        Mask native = active && !is_fluorescent_medium(medium, active);
        if (dr::any_or<true>(native))
            m = dr::select(native, fluo_detail::with_grad(m, medium->get_majorant(mei, native)), m);
        return m;
    }

    /// A derivative pass, after end_flight: the collision's σs, σn, σt (and d and μf
    /// where the medium fluoresces) with the derivatives of the medium's parameters at the
    /// detached point, values unchanged (Mitsuba's get_scattering_coefficients there), where
    /// `collided` (recording the loop, this keeps the AD graph smaller than sampling with
    /// gradients: test08's worker 15 GB, killed at 24 GB otherwise); and the flight's weight `w`
    /// times the relative derivative of its transmittance (tr over a detached pdf) where
    /// `weighted`. A native medium's majorant is its own
    /// (get_majorant; homogeneous: σt, whose transmittance then carries the derivative, as
    /// there are no null collisions), a fluorescent one's the flight's, detached (σn's
    /// derivative is −σt's; DerivativeMargin keeps null collisions possible).
    template <typename State>
    void attach_collision(State &ls, UnpolarizedSpectrum &w, UnpolarizedSpectrum &mu_f, Float &d, const Mask &weighted,
                          const Mask &is_fluo, const Mask &collided) const {
        MediumInteraction3f &mei = ls.mei;
        if (dr::none_or<false>(weighted || collided))
            return;
        UnpolarizedSpectrum m = majorant_of(ls.medium, mei, weighted || collided);
        Mask native = !is_fluorescent_medium(ls.medium, weighted || collided), flight = weighted && native;
        if (dr::any_or<true>(flight)) {
            Float t = dr::minimum(mei.t, ls.si.t) - mei.mint;
            w = dr::select(flight, w * fluo_detail::relative(dr::exp(-t * m)), w);
        }
        if (dr::any_or<true>(collided)) {
            auto [s, n, st] = ls.medium->get_scattering_coefficients(mei, collided);
            (void) n;
            mei.sigma_s = dr::select(collided, fluo_detail::with_grad(mei.sigma_s, s), mei.sigma_s);
            mei.sigma_t = dr::select(collided, fluo_detail::with_grad(mei.sigma_t, st), mei.sigma_t);
            mei.sigma_n = dr::select(collided, fluo_detail::with_grad(mei.sigma_n, m - st), mei.sigma_n);
            mei.combined_extinction = dr::select(collided, m, mei.combined_extinction);
        }
        if (!m_media.empty() && dr::any_or<true>(is_fluo)) {
            attach_fluorescent(ls.medium, mei, d, is_fluo);
            if constexpr (is_spectral_v<Spectrum>) {
                UnpolarizedSpectrum source = rates(ls.medium, mei.wavelengths, is_fluo).second * d;
                mu_f = dr::select(is_fluo, fluo_detail::with_grad(mu_f, source), mu_f);
            }
        }
    }

    /// A derivative pass: σs and the factor d (jit_sample_interaction's) at a fluorescent
    /// medium's collision sampled without gradients, with them (values unchanged), where `fluo`.
    void attach_fluorescent(const MediumPtr &medium, MediumInteraction3f &mei, Float &d, const Mask &fluo) const {
        auto [s, n, t] = medium->get_scattering_coefficients(mei, fluo);
        (void) n, (void) t;
        mei.sigma_s = dr::select(fluo, fluo_detail::with_grad(mei.sigma_s, s), mei.sigma_s);
        Float density = fluo_detail::dispatch_any(
            medium,
            [this](const Medium *m, const MediumInteraction3f &mei_, const Mask &on) {
                const BMedium *f = m_media_set.find(m);
                return f ? f->jit_density(mei_, on) : Float(0.f);
            },
            mei, fluo);
        d = dr::select(fluo, fluo_detail::with_grad(d, density), d);
    }

    /// K = 0: a fluorescent medium's real collision at `mei` (where `active`) picks, per hero
    /// wavelength, elastic scattering or a shift to λi (the docs' estimator): the ray's
    /// wavelengths become λi where shifted; `sigma_s` becomes both events' weight σs + μf
    /// (0 where none can go on). Returns where each wavelength shifted.
    template <typename State>
    WMask shift_collision(State &ls, const UnpolarizedSpectrum &mu_f, Sampler *sampler, const Mask &active,
                          double range_lo, double range_hi, UnpolarizedSpectrum &sigma_s) const {
        Wavelength ux, uy; // one 2D number, rotated per hero wavelength
        Point2f u = sampler->next_2d(active);
        ux[0] = u.x();
        uy[0] = u.y();
        fluo_detail::rotate_hero(ux);
        fluo_detail::rotate_hero(uy);
        auto [li, ok, rel] = fluo_detail::dispatch_any(
            ls.medium,
            [this, range_lo, range_hi](const Medium *m, const MediumInteraction3f &mei_, const Wavelength &u_,
                                       const Mask &on) {
                const BMedium *f = m_media_set.find(m);
                return f ? f->jit_excitation(mei_, u_, range_lo, range_hi, on)
                         : std::make_tuple(mei_.wavelengths, WMask(false), UnpolarizedSpectrum(1.f));
            },
            ls.mei, uy, active);
        WMask shifted = false;
        for (size_t j = 0; j < dr::size_v<UnpolarizedSpectrum>; ++j) {
            Float ss = dr::maximum(ls.mei.sigma_s[j], 0.f), sf = dr::maximum(mu_f[j], 0.f);
            Float total = ss + sf;
            Mask valid = total > 0.f && dr::isfinite(total);
            Mask elastic = ux[j] * total < ss;
            Mask shift = active && valid && !elastic && ok[j];
            // the chosen branch's rate over its detached probability: σs + μf in value, and
            // the derivative of that branch's rate alone (a chosen branch's rate is > 0)
            Float w = dr::detach(total) * fluo_detail::relative(dr::select(elastic, ss, sf * rel[j]));
            sigma_s[j] = dr::select(active, dr::select(valid && (elastic || shift), w, 0.f), sigma_s[j]);
            shifted[j] = shift;
        }
        ls.mei.wavelengths = dr::select(shifted, li, ls.mei.wavelengths);
        return shifted;
    }

    /// RGB variants: the 3×K block a shadow ray multiplies by the fluorescent media's
    /// operators on its way (a placeholder in spectral variants, K = 0).
    template <size_t K> using Block = std::conditional_t<K == 0, Float, Rows<(K == 0 ? 1 : K)>>;

    template <size_t K> struct ShadowState {
        Mask active;
        Ray3f ray;
        Float total_dist;
        Mask needs_intersection;
        MediumPtr medium;
        SurfaceInteraction3f si;
        MediumInteraction3f mei;
        Spectrum transmittance;
        UnpolarizedSpectrum mu_a; ///< μa of a fluorescent medium at the ray's wavelengths (density 1)
        Block<K> B;
        Mask met; ///< K > 0: a fluorescent medium acted on B
        /// Shadow::Recorded: 1 with the steps' derivatives (the transmittance's own product is
        /// formed without gradients)
        UnpolarizedSpectrum derivative;
        Sampler *sampler;
        DRJIT_STRUCT(ShadowState, active, ray, total_dist, needs_intersection, medium, si, mei, transmittance, mu_a, B,
                     met, derivative, sampler)
    };

    /// How transmit() treats derivatives: a render's (as volpath: the tracking's own), or, in a
    /// derivative pass, sampled without gradients and each step's factors with them at the
    /// detached collisions (majorants as attach_collision's; a fluorescent medium's σs and d in
    /// the reduced transport) multiplied into the transmittance (`Recorded`: Mitsuba's recorded
    /// AD) or backpropagated at once (`Replay`: fluo_prbvolpath; K > 0: replay_step()).
    enum class Shadow { Render, Recorded, Replay };

    /// K > 0, fluo_prbvolpath's replay of a shadow ray: what its value (light()'s) is made of
    /// besides the tracking, detached, and δL (times the estimate's MIS weight) it is weighed by.
    struct ShadowAdjoint {
        Color3f delta_L, emitter_val, rgb;
        Mask matrix, active;
        EmitterPtr emitter;
    };

    /// What the steps of one shadow ray share.
    struct ShadowWalk {
        const Scene *scene;
        Float max_dist, dist;
        UInt32 channel;
        Shadow mode;
        Spectrum adj;                ///< K = 0, Replay: δL times the estimate, detached
        const ShadowAdjoint *replay; ///< K > 0, Replay
    };

    /// K > 0: the emitter sample ds's value `emitter_val` seen from `at` through media
    /// (transmit), the contribution of a vertex whose operator towards it is B (3×K,
    /// `matrix`: the path is in matrix form there) or, in RGB form, `rgb` (the throughput
    /// times the vertex's value). (K = 0 multiplies transmit's transmittance in the loop.)
    /// `adjoint` (fluo_prbvolpath's replay: δL times the estimate's MIS weight, detached):
    /// the value with the derivatives of B, `rgb` and the emitter's value. B·T·c(le) is linear
    /// in B: T·c(le), K coefficients s, comes from continuations of the shadow ray carrying
    /// the identity's rows (⌈K/3⌉ clones of the sampler, as fluo_detail::future); then the ray
    /// itself is tracked again, its own factors' derivatives backpropagated (replay_step).
    template <size_t K, typename Interaction>
    Spectrum light(const Interaction &at, const DirectionSample3f &ds, const Spectrum &emitter_val,
                   const Scene *scene, Sampler *sampler, const MediumPtr &medium, const UInt32 &channel,
                   const Block<K> &B, const Color3f &rgb, const Mask &matrix, const Mask &active, Shadow mode,
                   const Color3f *adjoint = nullptr) const {
        if (adjoint) {
            // (tracked without gradients, s with the emitter's)
            Coeffs<K> s = fluo_detail::probe_coefficients<K, Coeffs<K>, Rows<K>>([&](const Rows<K> &probe, size_t) {
                ref<Sampler> clone = sampler->clone();
                auto [tr, B_out, met] = [&] {
                    dr::suspend_grad<Float> off;
                    return transmit<K>(at, ds, scene, clone.get(), medium, channel, probe, active, Shadow::Render);
                }();
                return Color3f(shadow_value<K>(tr, B_out, met, ds.emitter, emitter_val, Color3f(0.f), Mask(true), active));
            });
            ShadowAdjoint sa{ *adjoint, dr::detach(unpolarized_spectrum(emitter_val)), dr::detach(rgb), matrix, active,
                                 ds.emitter };
            auto [tr, B_out, met] = transmit<K>(at, ds, scene, sampler, medium, channel, dr::detach(B), active,
                                                Shadow::Replay, Spectrum(), &sa);
            return dr::select(met || matrix, Reduced::template apply<K>(B, s), rgb * emitter_val * tr);
        }
        auto [tr, B_out, met] = transmit<K>(at, ds, scene, sampler, medium, channel, B, active, mode);
        return shadow_value<K>(tr, B_out, met, ds.emitter, emitter_val, rgb, matrix, active);
    }

    /// K > 0: a shadow ray's value from what its tracking ended with (light()).
    template <size_t K>
    Spectrum shadow_value(const Spectrum &tr, const Rows<K> &B_out, const Mask &met, const EmitterPtr &emitter,
                          const Spectrum &emitter_val, const Color3f &rgb, const Mask &matrix,
                          const Mask &active) const {
        // through a fluorescent medium: B·diag(band albedos of the rest)·c(light)
        Rows<K> B_met = Reduced::template scale_columns<K>(B_out, m_reduced.template band_albedo<K>(tr));
        Color3f le = dr::select(met, emitter_val, emitter_val * tr);
        Color3f via_matrix = Reduced::template apply<K>(dr::select(met, B_met, B_out),
                                                        m_reduced.template emitter_coefficients<K>(emitter, le, active));
        return dr::select(met || matrix, via_matrix, rgb * emitter_val * tr);
    }

    /// The transmittance from `ref` to the emitter sample ds through media (ratio tracking;
    /// fluorescent media with their absorption majorant) and null interfaces, as volpath's
    /// sample_emitter. K > 0 (the reduced transport): a fluorescent medium's null collision
    /// multiplies B (given on entry) by its operator diag(μ̄ − σs)/μ̄ − (d/μ̄)·A, after the RGB
    /// transmittance so far (folded into B as per-band factors, then reset to 1); returns
    /// the transmittance, B and where a fluorescent medium was met (B multiplied out
    /// row-wise from the vertex). `mode`: see Shadow; the replay runs the same ratio tracking
    /// again (the sampler a clone of the first's) and backpropagates, K = 0, adj (δL times the
    /// next-event estimate, detached) times each step's relative derivative, K > 0 replay_step's.
    template <size_t K, typename Interaction>
    std::tuple<Spectrum, Block<K>, Mask> transmit(const Interaction &ref, const DirectionSample3f &ds,
                                                  const Scene *scene, Sampler *sampler, MediumPtr medium,
                                                  const UInt32 &channel, const Block<K> &B, Mask active,
                                                  Shadow mode = Shadow::Render, const Spectrum &adj = Spectrum(),
                                                  const ShadowAdjoint *replay = nullptr) const {
        Ray3f ray = ref.spawn_ray_to(ds.p);
        if constexpr (std::is_convertible_v<Interaction, SurfaceInteraction3f>)
            dr::masked(medium, ref.is_medium_transition()) = ref.target_medium(ray.d);
        ShadowWalk sw{ scene, ray.maxt, ds.dist, channel, mode, adj, replay };

        ShadowState<K> ss = { active,
                              ray,
                              Float(0.f),
                              Mask(true),
                              medium,
                              dr::zeros<SurfaceInteraction3f>(),
                              dr::zeros<MediumInteraction3f>(),
                              Spectrum(1.f),
                              UnpolarizedSpectrum(0.f),
                              B,
                              Mask(false),
                              UnpolarizedSpectrum(1.f),
                              sampler };
        track<K>(ss, sw);
        if (mode == Shadow::Recorded)
            ss.transmittance *= ss.derivative;
        return { ss.transmittance, ss.B, ss.met };
    }

    /// transmit()'s ratio tracking from the state ss to its end.
    template <size_t K> void track(ShadowState<K> &ss, const ShadowWalk &sw) const {
        dr::tie(ss) = dr::while_loop(
            dr::make_tuple(ss), [](const ShadowState<K> &ss) { return dr::detach(ss.active); },
            [this, sw](ShadowState<K> &ss) { shadow_step<K>(ss, sw); });
    }

    /// One step of transmit()'s ratio tracking: a null collision, a null surface or the ray's end.
    template <size_t K> void shadow_step(ShadowState<K> &ss, const ShadowWalk &sw) const {
        const Shadow mode = sw.mode;
        // a derivative pass: sampling without gradients, each factor's relative derivative in rel
        auto sampled = [&](auto &&f) {
            dr::suspend_grad<Float> off(mode != Shadow::Render);
            return f();
        };
        UnpolarizedSpectrum rel = 1.f;
        auto attached = [&](const Mask &m, auto &&factor) {
            if constexpr (dr::is_diff_v<Float>) {
                if (mode != Shadow::Render && dr::any_or<true>(m)) {
                    dr::resume_grad<Float> on;
                    rel = dr::select(m, rel * fluo_detail::relative(unpolarized_spectrum(factor())), rel);
                }
            }
        };
        Float remaining = sw.max_dist - ss.total_dist;
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
                dr::masked(ss.mu_a, segment) =
                    sampled([&] { return absorption_bound<K>(ss.medium, ss.ray.wavelengths, segment); });
            auto [mei, mu_f, fl, d] = sampled([&] {
                return sample_medium(ss.medium, ss.ray, ss.sampler->next_1d(active_medium), sw.channel,
                                     Float(0.f), ss.mu_a, UnpolarizedSpectrum(0.f), active_medium);
            });
            (void) mu_f;
            dr::masked(ss.mei, active_medium) = mei;
            dr::masked(ss.ray.maxt, active_medium && ss.medium->is_homogeneous() && ss.mei.is_valid()) =
                dr::minimum(ss.mei.t, remaining);
            Mask intersect = ss.needs_intersection && active_medium;
            if (dr::any_or<true>(intersect))
                dr::masked(ss.si, intersect) =
                    sampled([&] { return sw.scene->ray_intersect(ss.ray, intersect); });
            dr::masked(ss.mei.t, active_medium && ss.si.t < ss.mei.t) = dr::Infinity<Float>;
            ss.needs_intersection &= !active_medium;

            // reduced transport: fluorescent media act on B (weight 1 to escape, the
            // majorant being one for all bands)
            Mask reduced_fl = K > 0 ? Mask(fl && active_medium) : Mask(false);
            Mask is_spectral = ss.medium->has_spectral_extinction() && active_medium && !reduced_fl;
            Mask not_spectral = !ss.medium->has_spectral_extinction() && active_medium;
            if (dr::any_or<true>(is_spectral)) {
                Float t = dr::minimum(remaining, dr::minimum(ss.mei.t, ss.si.t)) - ss.mei.mint;
                UnpolarizedSpectrum tr = dr::exp(-t * ss.mei.combined_extinction);
                UnpolarizedSpectrum pdf = dr::select(ss.si.t < ss.mei.t || ss.mei.t > remaining, tr,
                                                     tr * ss.mei.combined_extinction);
                Float tr_pdf = channel_of(pdf, sw.channel);
                dr::masked(ss.transmittance, is_spectral) *= dr::select(tr_pdf > 0.f, tr / tr_pdf, 0.f);
                attached(is_spectral, [&] { return dr::exp(-t * majorant_of(ss.medium, ss.mei, is_spectral)); });
            }
            dr::masked(ss.total_dist, active_medium && ss.mei.t > remaining && ss.mei.is_valid()) = sw.dist;
            dr::masked(ss.mei.t, active_medium && ss.mei.t > remaining) = dr::Infinity<Float>;
            escaped = active_medium && !ss.mei.is_valid();
            active_medium &= ss.mei.is_valid();
            is_spectral &= active_medium;
            not_spectral &= active_medium;
            reduced_fl &= active_medium;
            dr::masked(ss.total_dist, active_medium) += ss.mei.t;
            dr::masked(ss.ray.o, active_medium) = ss.mei.p;
            dr::masked(ss.si.t, active_medium) = ss.si.t - ss.mei.t;
            dr::masked(ss.transmittance, is_spectral) *= ss.mei.sigma_n;
            dr::masked(ss.transmittance, not_spectral) *= ss.mei.sigma_n / ss.mei.combined_extinction;
            attached(is_spectral || not_spectral, [&] {
                UnpolarizedSpectrum m = majorant_of(ss.medium, ss.mei, active_medium);
                UnpolarizedSpectrum n = m - std::get<2>(ss.medium->get_scattering_coefficients(ss.mei, active_medium));
                return dr::select(is_spectral, n, n / m);
            });
            if constexpr (K > 0) {
                if (dr::any_or<true>(reduced_fl)) {
                    if (mode != Shadow::Render) // (sampled without gradients)
                        attach_fluorescent(ss.medium, ss.mei, d, reduced_fl);
                    Mask flush = reduced_fl && dr::any(ss.transmittance != 1.f);
                    ss.B = dr::select(flush,
                                      Reduced::template scale_columns<K>(
                                          ss.B, m_reduced.template band_albedo<K>(ss.transmittance)),
                                      ss.B);
                    dr::masked(ss.transmittance, reduced_fl) = 1.f;
                    ss.met |= reduced_fl;
                    Float mu = ss.mei.combined_extinction[0], inv_mu = dr::rcp(mu);
                    Coeffs<K> g = m_reduced.template band_albedo<K>(ss.mei.sigma_s);
                    for (size_t k = 0; k < K; ++k)
                        g[k] = (mu - g[k]) * inv_mu;
                    ss.B = dr::select(reduced_fl,
                                      medium_product<K>(ss.B, g, -d * inv_mu, &ReducedMedium::a,
                                                        which_media(ss.medium)),
                                      ss.B);
                }
            } else {
                (void) d;
            }
        }

        Mask intersect = active_surface && ss.needs_intersection;
        if (dr::any_or<true>(intersect))
            dr::masked(ss.si, intersect) = sampled([&] { return sw.scene->ray_intersect(ss.ray, intersect); });
        ss.needs_intersection &= !intersect;
        active_surface |= escaped;
        dr::masked(ss.total_dist, active_surface) += ss.si.t;

        active_surface &= ss.si.is_valid() && ss.active && !active_medium;
        if (dr::any_or<true>(active_surface)) {
            BSDFPtr bsdf = ss.si.bsdf(ss.ray);
            Spectrum v = bsdf->eval_null_transmission(ss.si, active_surface);
            dr::masked(ss.transmittance, active_surface) *= mode == Shadow::Render ? v : dr::detach(v);
            attached(active_surface, [&] { return v; }); // (its derivative once: in rel)
        }
        dr::masked(ss.ray, active_surface) = ss.si.spawn_ray(ss.ray.d);
        ss.ray.maxt = remaining;
        ss.needs_intersection |= active_surface;
        ss.active &= (active_medium || active_surface) &&
                     dr::any(unpolarized_spectrum(ss.transmittance) != 0.f);
        if constexpr (K > 0) {
            // a fluorescent medium's operator B carries the weight where it was met
            // (transmittance stays 1 there): once B is zero (absorbed: in an optically
            // thick medium a few null collisions), the ray stops as the spectral one
            // does at a zero transmittance, instead of crossing every null collision
            ss.active &= !ss.met || dr::any(ss.B != 0.f);
        }
        Mask transition = active_surface && ss.si.is_medium_transition();
        dr::masked(ss.medium, transition) = ss.si.target_medium(ss.ray.d);
        if constexpr (dr::is_diff_v<Float>) {
            if (mode == Shadow::Recorded) {
                dr::resume_grad<Float> on;
                ss.derivative *= rel;
            } else if (mode == Shadow::Replay) {
                dr::resume_grad<Float> on;
                if constexpr (K == 0) {
                    if (Spectrum weighted = sw.adj * rel; dr::grad_enabled(weighted))
                        dr::backward_from(weighted);
                } else if constexpr (!is_polarized_v<Spectrum>) {
                    replay_step<K>(ss, sw, rel);
                }
            }
        }
    }

    /// K > 0, fluo_prbvolpath's replay of a shadow ray, after a step whose factors carry
    /// derivatives: the ray's value (shadow_value) is linear in the transmittance so far t
    /// (3 values; B given) and in B (t given), so the step's factors contribute
    /// δLᵀ·J_t·(t ⊙ rel) + δLᵀ·B'·s, where B' is B with this step's derivatives, the columns
    /// of J_t come from continuations of the ray carrying the unit vectors in place of t, and s
    /// (K coefficients) from continuations carrying the identity's rows in place of B (clones
    /// of the sampler, without gradients: the same steps). Time grows with the square of the
    /// number of steps (as fluo_detail::future's); the ray goes on detached.
    template <size_t K> void replay_step(ShadowState<K> &ss, const ShadowWalk &sw, const Color3f &rel) const {
        Rows<K> B = ss.B; // (with this step's derivatives)
        ss.B = dr::detach(ss.B);
        ss.mei = dr::detach(ss.mei);
        const ShadowAdjoint &sa = *sw.replay;
        auto value = [&](auto &&set) { // the ray's value from ss on, with a part of its state replaced
            dr::suspend_grad<Float> off;
            ShadowState<K> cs = ss;
            ref<Sampler> clone = ss.sampler->clone();
            cs.sampler = clone.get();
            set(cs);
            ShadowWalk render = sw;
            render.mode = Shadow::Render;
            track<K>(cs, render);
            return Color3f(shadow_value<K>(cs.transmittance, cs.B, cs.met, sa.emitter, sa.emitter_val, sa.rgb,
                                           sa.matrix, sa.active));
        };
        Float weighted = 0.f;
        if (dr::grad_enabled(rel)) {
            for (size_t j = 0; j < 3; ++j) {
                Color3f c = value([j](ShadowState<K> &cs) {
                    cs.transmittance = 0.f;
                    cs.transmittance[j] = 1.f;
                });
                weighted += dr::dot(sa.delta_L, c) * ss.transmittance[j] * rel[j];
            }
        }
        if (dr::grad_enabled(B)) {
            Coeffs<K> s = fluo_detail::probe_coefficients<K, Coeffs<K>, Rows<K>>(
                [&](const Rows<K> &probe, size_t) { return value([&probe](ShadowState<K> &cs) { cs.B = probe; }); });
            weighted += dr::dot(sa.delta_L, Reduced::template apply<K>(B, s));
        }
        if (dr::grad_enabled(weighted))
            dr::backward_from(weighted);
    }

    // ------------------------------------------------ RGB: reduced transport

    /// A fluorescent medium's reduced operators (RGB variants), 1/m at density 1.
    struct ReducedMedium {
        const Medium *medium;
        std::vector<double> a, f;
        std::vector<double> f_rows; ///< Σ_j |F_kj|/(4π) per band k: its re-emission into band k
        std::vector<double> f_max;  ///< { the largest of f_rows }
        std::vector<double> a_max;  ///< { the largest diagonal entry of A }: the majorant's bound
        /// Per parameter of the medium carrying a gradient: θ − detach(θ) and ∂A/∂θ, ∂F/∂θ
        /// (K×K; none without)
        std::vector<std::pair<Float, std::vector<double>>> a_t, f_t;
    };

    /// What a fluorescent medium's majorant must cover, 1/m at density 1: μa at the
    /// wavelengths (spectral); in the reduced transport (K > 0) μa's sRGB and the largest
    /// diagonal entry of its reduced absorption A (a bound over the bands, narrower than
    /// the spectrum's maximum: fewer null collisions, each 3K² products).
    template <size_t K>
    UnpolarizedSpectrum absorption_bound(const MediumPtr &medium, const Wavelength &lambda, const Mask &active) const {
        UnpolarizedSpectrum mu_a = rates(medium, lambda, active).first;
        if constexpr (K > 0)
            mu_a = dr::maximum(mu_a, per_medium(which_media(medium), &ReducedMedium::a_max, 0));
        return mu_a;
    }

    /// Per lane, whether `medium` is each of the scene's fluorescent media (compared by
    /// pointer; a handful per scene: no allocation per event).
    using MediaMasks = fluo_detail::Scratch<Mask, 4>;
    MediaMasks which_media(const MediumPtr &medium) const {
        MediaMasks which(m_rmedia.size());
        for (size_t i = 0; i < m_rmedia.size(); ++i)
            which[i] = medium == MediumPtr(m_rmedia[i].medium);
        return which;
    }

    /// Entry i of a fluorescent medium's constant table (`field`) per lane: a select over the
    /// media (a constant in the kernel for one medium; 0 without any: the llvm/cuda loop
    /// traces every branch, also where no lane takes it).
    Float per_medium(const MediaMasks &which, std::vector<double> ReducedMedium::*field, size_t i) const {
        if (m_rmedia.empty())
            return Float(0.f);
        Float v = (float) (m_rmedia[0].*field)[i];
        for (size_t m = 1; m < m_rmedia.size(); ++m)
            v = dr::select(which[m], (float) (m_rmedia[m].*field)[i], v);
        return v;
    }

    /// R·diag(g) + s·R·M, M a fluorescent medium's A or F (`field`): a null collision's
    /// operator (g = μ̄ − σs, s = −d) or a real one's source (g = σs∘p, s = d/(4π)), each
    /// times the event's weight. 3K² products; entries that are 0 for every medium are skipped.
    template <size_t K>
    Rows<K> medium_product(const Rows<K> &R, const Coeffs<K> &g, const Float &s,
                           std::vector<double> ReducedMedium::*field, const MediaMasks &which) const {
        Rows<K> out = Reduced::template scale_columns<K>(R, g);
        for (size_t j = 0; j < K; ++j) {
            std::array<Float, 3> acc = { 0.f, 0.f, 0.f };
            bool any = false;
            for (size_t k = 0; k < K; ++k) {
                bool zero = true;
                for (const ReducedMedium &r : m_rmedia)
                    zero &= (r.*field)[k * K + j] == 0.0;
                if (zero)
                    continue;
                Float m = per_medium(which, field, k * K + j);
                for (size_t r = 0; r < 3; ++r)
                    acc[r] = any ? dr::fmadd(R[r * K + k], m, acc[r]) : R[r * K + k] * m;
                any = true;
            }
            if (any)
                for (size_t r = 0; r < 3; ++r)
                    out[r * K + j] = dr::fmadd(s, acc[r], out[r * K + j]);
        }
        // a medium's parameters carrying gradients: + δ·s·R·∂M/∂θ with δ = θ − detach(θ) (0 in
        // value: R and s detached in it, one attached factor per product, not K² attached entries)
        for (size_t m = 0; m < m_rmedia.size(); ++m) {
            const ReducedMedium &rm = m_rmedia[m];
            for (const auto &[delta, dm] : field == &ReducedMedium::a ? rm.a_t : rm.f_t) {
                Float f = dr::select(which[m], dr::detach(s) * delta, 0.f);
                for (size_t j = 0; j < K; ++j)
                    for (size_t r = 0; r < 3; ++r) {
                        Float acc = 0.f;
                        for (size_t k = 0; k < K; ++k)
                            if (dm[k * K + j] != 0.0)
                                acc = dr::fmadd(dr::detach(R[r * K + k]), (float) dm[k * K + j], acc);
                        out[r * K + j] = dr::fmadd(f, acc, out[r * K + j]);
                    }
            }
        }
        return out;
    }

    /// Null and real probabilities over the bands (the docs' reduced transport): the bands
    /// R carries (w_k: column maxima) in place of the hero wavelengths.
    template <size_t K>
    std::pair<Float, Float> band_tracking(const Rows<K> &R, const Coeffs<K> &sigma_s, const Float &d,
                                          const Float &majorant, const Float &inv_len,
                                          const MediaMasks &which) const {
        Coeffs<K> w = Reduced::template column_max<K>(R);
        Float q_null = 0.f, q_real = 0.f, kappa = 0.f;
        for (size_t k = 0; k < K; ++k) {
            Mask live = w[k] > 0.f;
            Float st = dr::maximum(dr::fmadd(d, per_medium(which, &ReducedMedium::a, k * K + k), sigma_s[k]), 0.f);
            Float source = dr::fmadd(d, per_medium(which, &ReducedMedium::f_rows, k), dr::maximum(sigma_s[k], 0.f));
            Float rate = dr::select(inv_len > 0.f, dr::minimum(source, inv_len), source);
            q_null = dr::select(live, dr::maximum(q_null, w[k] * dr::abs(majorant - st)), q_null);
            q_real = dr::select(live, dr::maximum(q_real, w[k] * st), q_real);
            kappa = dr::select(live, dr::maximum(kappa, rate), kappa);
        }
        return collision_probabilities(q_null, q_real, kappa, majorant);
    }

    /// R·W·s with W = diag(σs∘p) + d·iso·F: a fluorescent medium's real collision for the
    /// elastic weight p (phase value, or weight) and the isotropic re-emission's iso (1/4π,
    /// over the pdf if sampled), s = 1/(μ̄ p_real).
    template <size_t K>
    Rows<K> source_product(const Rows<K> &R, const Coeffs<K> &sigma_s, const Color3f &p, const Float &d,
                           const Float &iso, const Float &s, const MediaMasks &which) const {
        Coeffs<K> pk = m_reduced.template band_albedo<K>(p);
        Coeffs<K> g;
        for (size_t k = 0; k < K; ++k)
            g[k] = sigma_s[k] * pk[k] * s;
        return medium_product<K>(R, g, d * iso * s, &ReducedMedium::f, which);
    }

    ref<MonteCarloIntegrator<Float, Spectrum>> m_volpath; ///< the render without fluorescence
    std::vector<const BMedium *> m_media;
    fluo_detail::InterfaceSet<Medium, BMedium> m_media_set; ///< m_media, found per event by address
    std::vector<ReducedMedium> m_rmedia;   ///< RGB variants: the fluorescent media's operators
    bool m_fluorescent = false;
};

static const bool fluo_volpath_jit_registered =
    (fluo_detail::register_plugin<FluoVolpath>("fluo_volpath", ObjectType::Integrator),
     fluo_detail::register_plugin<FluoVolpath>("fluo_prbvolpath", ObjectType::Integrator), true);

NAMESPACE_END(mitsuba)
