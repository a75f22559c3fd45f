// fluo_path, one class template for every variant it serves: Mitsuba's `path` loop
// (dr::while_loop; one kernel in the llvm/cuda variants) with fluorescence (the
// documentation below has the estimators): per-lane wavelength shifting in spectral
// variants, the 3×K reduced matrix throughput in RGB ones. Fluorescent BSDFs are reached
// through dr::dispatch (a direct call in the scalar variants) and the interface of
// fluo_bispectral.h; Rust runs once per render (the scene scan, reduced matrices).
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

#include "fluo_common.h"
#include "fluo_bispectral.h"
#include "fluo_reduced.h"
#include "fluo_path_scene.h"
#include "fluo_integrator.h"

NAMESPACE_BEGIN(mitsuba)

/**!

.. _integrator-fluo_path:

Wavelength-shifting path tracer (:monosp:`fluo_path`)
-----------------------------------------------------

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
 * - basis
   - |string|
   - RGB variants only: transport basis for fluorescence, ``rgb`` (3 channels),
     ``xyzu`` (CIE 1931 XYZ plus a UV band), ``x7`` (7 bands: X split in three, Y in two,
     Z, U) or ``auto`` (x7's six visible bands and, in place of U, one or two bands built
     at render start from the scene's ``fluo_illuminant`` spectra: the part of a light
     outside the bands before it, so that light is in the basis's span and a material lit
     directly by it is reduced exactly, UV lamps included; one or two distinct spectra each
     exactly on its own (K = 7, or 8 where a second band holds more than 1e-3 of its
     light), more: the one with the most light outside the visible bands exactly, the
     others exactly together; light after fluorescent or coloured bounces stays
     approximate as in ``x7``; without spectral lights it is ``x7``). (Default: ``auto``:
     on the ``fluo bench`` scenes its mean ΔE00 floor against the spectral reference is at or below
     ``x7``'s on every surface scene (blacklight box 2.48 against 6.63, measured box 0.73
     against 0.84, jung box 0.72 against 0.75, the rest equal); README's generated bench
     table has the numbers. With one light spectrum it costs what ``x7`` costs per vertex
     (K = 7; cost row ``vertex_auto_*``: 0.98-0.99 of x7's time), with two K = 8, and a
     reduction of each material per render, as every basis does. One band for the sum of
     a D65 sky and a 365 nm lamp rendered a dye's glow 16 % too dark where ``x7`` was 10 %
     too bright; with a band per light it is exact for light arriving directly from
     either.) Which basis when (``fluo-rs saturated-report`` and the second table of
     ``fluo bench`` measure it per basis): ``auto`` whenever the lights are
     ``fluo_illuminant`` spectra, above all under narrow UV lamps, where every fixed basis
     is coarse: one UV band averages a dye's absorption over 300-400 nm (a brightener under
     a 365 nm lamp glows ~5x too dark in ``xyzu``/``x7``, and not at all in ``rgb``), while
     ``auto`` renders a grey room with a brightener, a green dye, a measured matrix and a
     quantum-dot coating under a 365 nm lamp and a dim D65 fill within mean ΔE00 0.28
     (8×8-pixel blocks) of the spectral render where ``x7`` is 2.42, the same room under an
     FL2 tube 0.23 against 0.46 (two spectral seeds differ by 0.19 and 0.11;
     ``tests/python/test_adaptive_basis.py``); ``x7`` for saturated, narrow-band emitters
     under RGB lights (a pure green dye keeps its luminance within 20 % under daylight and
     incandescent light, where ``rgb`` and ``xyzu`` lose a third or more); ``xyzu`` when
     materials are broad and 4×4 matrices matter; ``rgb`` only for scenes without UV
     excitation (it has no UV band: an optical brightener's reradiation under daylight all
     but vanishes) or to compare with a plain RGB renderer. With a fixed basis fluo_path
     warns once per scene when an emitter is mostly ultraviolet. Light after several
     fluorescent or coloured bounces is approximate in every basis.
 * - method
   - |string|
   - RGB variants only: reduction of the reradiation, ``ours`` (dual basis, Fichet et
     al. 2024 eq. 15) or ``naive`` (eq. 7, for comparison only). (Default: ``ours``)
 * - lambda_min
   - |float|
   - Shortest excitation wavelength the integrator will ever shift to, nm, in
     [200, 360]. Spectrally defined emitters reach below the camera's 360 nm down
     to here. (Default: 300)

Unidirectional path tracing with next-event estimation and MIS, Russian roulette and
``max_depth``/``rr_depth``/``hide_emitters`` exactly as Mitsuba's ``path``, extended
with fluorescence (wavelength shifting) for fluo's bispectral BSDFs (``fluo_jung``
and the other ``fluo_*`` materials) in the spectral variants. Like ``path`` it does not
trace participating media: a scene with media gets one warning per scene pointing to
``fluo_volpath`` (which renders media, fluorescent or not).

**Variants.** One implementation serves ``scalar_*``, ``llvm_ad_*`` and ``cuda_ad_*``:
the estimators below run inside Mitsuba's ``dr::while_loop`` (one kernel per render in
the llvm/cuda variants): per lane and hero wavelength the elastic/shift choice, or the
3×K matrix throughput with Mitsuba's RGB throughput until the first fluorescent vertex.
The fluorescent materials are reached through ``dr::dispatch`` (a direct call in the
scalar variants) and evaluate baked tables and closed forms per lane; no variant calls
Rust per vertex. With more than 8 fluorescent materials in the llvm/cuda variants, those
that do not vary over the surface and carry no gradient are read from one table per lane
(by the BSDF's registry id) instead: in RGB their operators, formed once per render, and a
direction-dependent lobe's node weights and matrices (the lobe itself from one member of
the class); in spectral variants each class's data joined (``fluo_jung``'s dye numbers,
``fluo_qd``'s coating tables), one choice and one reradiation lobe per class; and in both,
a coating's own BSDF (its microfacet lobe over its coating and substrate, which Mitsuba's
call over the scene's BSDFs would trace once per coating) is evaluated per class from the
joined tables, one class per distribution and substrate, the call then tracing nothing for
those coatings (``fluo_volpath`` alike). Dr.Jit traces a dispatch once per material, which
made 200 distinct dyes compile 2.3× as long as 200 ``diffuse`` (1.3–1.5× so), and 200
coatings load and first-render 4.3× as long as 200 ``roughconductor`` (with their choice and
lobe joined: spectral 2.5×, RGB 2.2×; with their own BSDF joined too: spectral 1.4× in 1.5×
the memory, every coating's tables being one block of one array which the joined class reads
in place; RGB 1.7×).
**Gradients** (``llvm_ad_*``, ``cuda_ad_*``): the materials' probabilities are detached,
their values differentiable, so ``mi.render`` with ``params`` gives gradients of dye
parameters; a sampled direction that moves with a parameter (a roughness) is detached and
the BSDF's value differentiated there, as Mitsuba's ``path`` does (differentiating the
sample's motion gave d/dalpha of the wrong sign, for ``roughconductor`` as for ``fluo_qd``).

**Polarized variants** (``scalar_spectral_polarized``, ``llvm_ad_spectral_polarized``,
``cuda_ad_spectral_polarized``): the throughput is a Mueller matrix as in ``path``; the
elastic lobes are the materials' own (a Lambertian lobe is a depolarizer, ``fluo_qd``'s
substrate reflects with ``roughconductor``'s Mueller matrix), and light re-emitted at a
shifted wavelength leaves unpolarized: those wavelengths' entries are a depolarizer
(Stokes s1..s3 of reradiation are 0). Nested in Mitsuba's ``stokes`` (or ``aov``) integrator,
the first sample of a scene prepares it (the scan below).

**Simulate only what the scene calls for.** At the start of each render the scene is
scanned once: the fluorescent BSDFs (those implementing fluo's bispectral interface
and re-emitting at all) and the spectral range of every emitter's radiance texture.
Light exists only where emitters emit or fluorescence re-emits, so excitation is
sampled only inside R = [max(emitters' min, lambda_min), max(emitters' max,
emission max)]. A material whose absorption band misses R is treated as a plain
BSDF. With nothing left, this integrator runs exactly Mitsuba's ``path`` (the same
loop, the same random numbers: identical images), in every variant.

**Fluorescence in RGB (reduced transport).** In the RGB variants a scene with fluorescent
materials is rendered with matrix throughput (Fichet et al. 2024, sec. 5.1, adjoint
transport). A camera path carries Mitsuba's RGB throughput t, exactly as ``path`` does,
until it meets its first fluorescent vertex: light that never meets a fluorescent
material (native walls lit by native or ``fluo_illuminant`` lights) renders exactly as
``path`` renders it, under every basis (before this, native vertices were always basis
diagonals, and the walls of a Cornell box with one fluorescent object came out 13.7 %
(``xyzu``) and 4.8 % (``x7``) off). At the first fluorescent vertex t becomes a 3×K
matrix R = diag(t)·O (O from K basis coefficients to linear sRGB), which from then on
is multiplied at each vertex by a K×K matrix: the material's
reduced operator (core/src/reduce/): the whole operator (elastic diagonal and reradiation,
as in the paper) when its elastic reflectance is known spectrally (sigmoid
``coefficients``, measured data), otherwise the reduced reradiation plus the elastic
RGB albedo (e.g. a texture) as a diagonal. Native BSDFs met after a fluorescent
vertex act as diagonal matrices: their RGB value v becomes per-band albedos
a_k = (F v)_k / (F 1)_k, with F the map from RGB light to basis coefficients (for
``basis="rgb"`` simply v). Emitters contribute R·c: for emitters whose radiance is a
``fluo_illuminant`` the coefficients of its spectrum (including the UV band, so a UV-only
lamp still excites fluorescence), for others F times their RGB radiance. Reduced matrices
have negative entries (the dual basis has negative lobes), so coefficients along a path
are signed and kept so; only the final linear sRGB of each sample is clipped at zero
(out-of-gamut colours such as a saturated 520 nm emission have negative sRGB red, which
Mitsuba's RGB film would otherwise warn about on every sample). This clips a little
energy from colours outside the sRGB gamut, which an sRGB image cannot show anyway.

**Wavelength shifting.** The camera path carries four hero wavelengths, each with its
own throughput. At a fluorescent vertex, each wavelength λo (the one travelling
towards the camera) decides on its own between the elastic event (λ kept) and a shift
to an excitation wavelength λi < λo sampled by the material; directions stay shared.
Emitter sampling and later bounces then see the shifted wavelengths; the film still
receives the camera wavelengths.

*Why the estimator is unbiased.* For a fixed λo the vertex must estimate
``f_e(λo) L(λo) + ∫_R f_fl(λi, λo) L(λi) dλi`` (elastic plus reradiation; L is the
incident radiance, which is zero outside R). Let ``w_e`` be the elastic albedo and
``w_f`` the reradiated albedo reaching λo from excitations in R (both from the
material). We pick the elastic event with probability ``p_e = w_e / (w_e + w_f)``
and weight it by ``1/p_e``, or the shift with probability ``1 − p_e``, sampling λi
with density ``p(λi)`` over R and weighting by ``1/((1 − p_e) p(λi))``. The expectation
of either branch's weighted integrand is its term above, and their sum is the whole.
``p_e`` is positive exactly where ``f_e`` is and ``1 − p_e`` wherever the shift
integrand is, so no contribution is skipped. (``w_f`` may be positive where the shift
integrand is zero: the shift then samples nothing and the elastic branch's ``1/p_e``
weight makes up for it, so only the variance changes. That is why ``w_f`` may be
approximate, as some materials' per-lane estimate is: ``fluo_jung``'s takes the
absorption's integral over R times the Jacobian at the absorption peak.) After the
choice the vertex is an ordinary (wavelength-changing) BSDF: next-event estimation and
BSDF sampling estimate the incident radiance L(λi, ω) with the usual MIS weights, which
do not depend on wavelength. Each hero wavelength is an independent estimator of its
camera wavelength's radiance, so the film's wavelength weights stay valid.

Spatially varying fluorescence (``fluo_jung`` with a ``color`` texture or textured
parameters, ``fluo_qd`` with textured parameters, ``fluo_matrix``/``fluo_gmm`` with an
``index`` texture) is resolved per vertex by the material's choice (the bispectral
interface's ``jit_choose``): each vertex uses its own model and intersects its
excitation band with R.

Fluorescent materials may be wrapped in ``twosided``, ``blendbsdf``, ``mask``,
``normalmap`` and ``bumpmap`` (nested too; every variant): at each vertex the integrator
resolves the wrapper, per lane, to the BSDF that acts there — ``twosided``: the front or
back child, with the local frame mirrored for the back side exactly as ``twosided`` does;
``blendbsdf``: child 1 with probability w(si), else child 0; ``mask``: the nested BSDF
with probability opacity(si), else a null (pass-through) interaction, as ``mask`` samples
it; ``normalmap`` and ``bumpmap``: the nested BSDF in the perturbed shading frame, which
every lobe of the vertex then uses (elastic and fluorescent), with the adapters' rule
that a direction on different sides of the two frames carries nothing — and treats that child
as an unwrapped material. The selections are unbiased: renders equal the wrapper's within
noise. Any other BSDF around a fluorescent one is refused with an error at render start
(the first access the integrator has to the scene) rather than rendered without its
fluorescence. Mitsuba's own integrators
(``path``, ...) render only the elastic part of fluorescent materials, and say so once
per scene.

**Path replay (``fluo_prb``).** The same class registered as ``fluo_prb`` renders exactly
what ``fluo_path`` renders (the same loop, random numbers and images) and differs only in
reverse-mode differentiation (``mi.render(scene, params)`` followed by ``dr.backward``):
instead of differentiating the recorded loop, whose memory grows with the path depth,
it replays each path (path replay backpropagation, Vicini et al. 2021, as Mitsuba's
``prb``) in three passes with the render's seed: the film's derivative per sample (δL),
the primal radiance L, then the same paths again (same vertices, elastic/shift choices
and wavelengths) carrying the radiance still to come, each vertex backpropagating δL
times its emission, its next-event estimate and the rest of the path through the
relative derivative of its weight (the shift's reradiation included), inside the loop:
memory independent of depth (one backward pass of the fluorescent Cornell box at 256²,
64 spp, ``max_depth`` 8: the cost row ``llvm_backward_memory``). Sampling is detached
(directions, wavelength choices and probabilities carry no derivative; each vertex
differentiates the BSDF's and the emitter's values at the sampled directions, as ``prb``
does); the surface interactions are detached, so shapes get no gradient (geometry needs
reparameterisation, which neither ``fluo_path`` nor this replay does). A render in several
passes (``samples_per_pass``, or more than 2^32 samples) is refused. Every AD variant
replays (``llvm_ad_spectral``, ``llvm_ad_rgb``, their cuda twins; not the polarized ones, below). In an RGB variant with
fluorescent materials the reduced transport carries a 3×K matrix throughput R, and the
radiance still to come after a vertex is R·r for K basis coefficients r that the
primal's 3 RGB values do not determine (nor can a vertex's K×K factor be divided out of
them stably); there each vertex continues its path to the end with the same random
numbers, without gradients, carrying the identity's rows in place of R (⌈K/3⌉
continuations of 3 rows) to get r. Memory stays independent of depth; time grows with
its square (the RGB row ``llvm_backward_memory_rgb``). The continuations' roulette
decides on their own throughput (unbiased; with roulette off the replay's derivatives
equal the recorded loop's to 1e-6). Polarized variants refuse it.

.. tabs::
    .. code-tab:: xml

        <integrator type="fluo_path">
            <integer name="max_depth" value="8"/>
        </integrator>

        <!-- gradients with memory independent of path depth -->
        <integrator type="fluo_prb">
            <integer name="max_depth" value="8"/>
        </integrator>
*/

template <typename Float, typename Spectrum>
class FluoPath final : public FluoIntegrator<Float, Spectrum> {
public:
    MI_IMPORT_BASE(FluoIntegrator, m_max_depth, m_rr_depth, m_hide_emitters, m_lambda_min, m_reduced, m_bsdfs,
                   m_range_lo, m_range_hi, m_wrappers, m_directional, m_varying, m_differentiating, m_replayer)
    MI_IMPORT_TYPES(Scene, Sensor, Sampler, Medium, Emitter, EmitterPtr, BSDF, BSDFPtr, Shape, Texture)
    using typename Base::Bispectral;
    using typename Base::Reduced;
    using typename Base::Wrappers;
    template <size_t K> using Coeffs = typename Base::template Coeffs<K>;
    template <size_t K> using Rows = typename Base::template Rows<K>;

    static constexpr const char *Plugin = "fluo_path";

    FluoPath(const Properties &props) : Base(props, Plugin, "fluo_prb", "auto") {}

    std::string to_string() const override {
        std::ostringstream oss;
        oss << "FluoPath[" << std::endl
            << "  max_depth = " << m_max_depth << "," << std::endl
            << "  rr_depth = " << m_rr_depth << "," << std::endl
            << "  lambda_min = " << m_lambda_min << "," << std::endl
            << "  basis = " << m_reduced.name() << " (K = " << m_reduced.bands() << ")," << std::endl
            << "  fluorescent_bsdfs = " << m_bsdfs.size() << "," << std::endl
            << "  excitation_range = [" << m_range_lo << ", " << m_range_hi << "]" << std::endl
            << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(FluoPath)

protected:
    /// Once per render: the fluorescent BSDFs and the wrappers around them, the emitters'
    /// spectral range and, in RGB variants, reduced matrices and the emitters' basis
    /// coefficients.
    void prepare(Scene *scene) override {
        fluo_detail::warn_if_media(Plugin, scene, m_media_warned);
        std::vector<Bispectral *> bsdfs = this->scan(scene, 0.0);
        m_reduced.prepare(scene, bsdfs, false);
        m_bsdfs.assign(bsdfs);
        m_varying = m_directional && m_reduced.varying();
    }

    /// trace() with the carried throughput of this render: the reduced transport's K bands
    /// in RGB variants with fluorescent materials, else Mitsuba's throughput.
    std::pair<Spectrum, Bool> trace_sample(const Scene *scene, Sampler *sampler, const RayDifferential3f &ray,
                                           const Medium * /* medium */, Float * /* aovs */, Bool active,
                                           bool adjoint, bool clip) const override {
        return this->with_bands(clipped(), [&](auto k) {
            return trace<decltype(k)::value>(scene, sampler, ray, active, adjoint, clip);
        });
    }
    /// The reduced transport (RGB variants with fluorescent materials) clips per sample.
    bool clipped() const override { return m_reduced.size() > 0; }

private:
    /// First intersection of a camera ray, skipping area emitters when they are hidden
    /// (as path.cpp does at depth 0).
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

    static Float mis_weight(const Float &a, const Float &b) { return fluo_detail::mis_weight(a, b); }


    // ------------------------------------------------------------ the loop

    /// What a path carries. K = 0: Mitsuba's throughput (the spectral variants shift its
    /// wavelengths at fluorescent vertices; a scene without fluorescence is `path`).
    struct Throughput {
        Spectrum throughput;
        DRJIT_STRUCT(Throughput, throughput)
    };
    /// K > 0 (RGB with fluorescence, the reduced transport): FluoIntegrator::MatrixThroughput.
    template <size_t K> using Carried = typename Base::template Carried<K, Throughput>;

    template <size_t K> struct LoopState {
        Ray3f ray;
        PreliminaryIntersection3f pi;
        Carried<K> c;
        Spectrum result;
        Float eta;
        UInt32 depth;
        Mask valid_ray;
        Interaction3f prev_si;
        Float prev_bsdf_pdf;
        Bool prev_bsdf_delta, active;
        Sampler *sampler;
        DRJIT_STRUCT(LoopState, ray, pi, c, result, eta, depth, valid_ray, prev_si, prev_bsdf_pdf, prev_bsdf_delta,
                     active, sampler)
    };

    /// What the vertices of one trace() share: whether it is fluo_prb's third pass (the
    /// replay), and that pass's adjoint radiance δL.
    struct Walk {
        bool adjoint = false, differentiating = false; ///< the replay; a recorded derivative pass
        Spectrum delta_L;
    };

    /// path.cpp's loop; what differs between the carried throughputs is marked K == 0 / K > 0.
    /// `adjoint`: fluo_prb's third pass, the replay (FluoIntegrator). K = 0: `result` holds
    /// the radiance still to come (the primal's, less what the vertices passed gave); K > 0:
    /// each vertex's radiance still to come is estimated by future(). `clip`: K > 0 clips
    /// out-of-gamut colours per sample (the replay's primal pass keeps them: their sign masks δL).
    template <size_t K>
    std::pair<Spectrum, Bool> trace(const Scene *scene, Sampler *sampler, const RayDifferential3f &ray_,
                                    Bool active, bool adjoint = false, bool clip = true) const {
        if constexpr (K > 0 && !is_rgb_v<Spectrum>) {
            return { 0.f, false };
        } else {
            Carried<K> start;
            if constexpr (K == 0)
                start = { Spectrum(1.f) };
            else
                start = { Color3f(1.f), dr::zeros<Rows<K>>(), Mask(false) };
            LoopState<K> ls = { Ray3f(ray_), dr::zeros<PreliminaryIntersection3f>(), start, Spectrum(0.f),
                                Float(1.f), UInt32(0), Mask(!m_hide_emitters && scene->environment() != nullptr),
                                dr::zeros<Interaction3f>(), Float(1.f), Bool(true), active, sampler };
            ls.pi = camera_intersection(scene, ls.ray, ls.active);
            Walk w{ adjoint, m_differentiating, Spectrum() };
            if constexpr (dr::is_diff_v<Float>) {
                if (adjoint) {
                    if constexpr (K == 0)
                        ls.result = m_replayer.primal();
                    w.delta_L = m_replayer.adjoint();
                }
            }
            this->loop(ls, [&](LoopState<K> &s) { step<K>(scene, s, w); });
            // K > 0: out-of-gamut colours are clipped per sample (the docs' reduced transport)
            if constexpr (K > 0)
                if (clip)
                    ls.result = dr::maximum(ls.result, 0.f);
            return { dr::select(ls.valid_ray, ls.result, 0.f), ls.valid_ray };
        }
    }

    /// One vertex of trace()'s loop.
    template <size_t K> void step(const Scene *scene, LoopState<K> &ls, const Walk &w) const {
        BSDFContext bsdf_ctx;
        Carried<K> &c = ls.c;
        Carried<K> next; // K > 0, the replay: the throughput after this vertex, with gradients
        // the replay: this vertex's values with gradients, what it gives (Lo) backpropagated
        dr::resume_grad<Float> attached(w.adjoint);
        Spectrum Lo = 0.f;
        auto backpropagate = [&] {
            if constexpr (dr::is_diff_v<Float>) {
                if (dr::grad_enabled(Lo)) {
                    Spectrum weighted = w.delta_L * Lo;
                    dr::backward_from(weighted);
                }
            }
        };
        SurfaceInteraction3f si = ls.pi.compute_surface_interaction(ls.ray, +RayFlags::All);
        if (w.adjoint) // the replay differentiates materials and emitters, not geometry
            si = dr::detach(si);

        // ---------------------- Direct emission ----------------------
        if (dr::any_or<true>(si.emitter(scene) != nullptr)) {
            auto [emitter, le, mis_bsdf] = hit_emission(scene, si, ls);
            if constexpr (K == 0) {
                if (w.adjoint) {
                    Lo = c.throughput * le * mis_bsdf;
                    ls.result -= dr::detach(Lo);
                } else {
                    ls.result = dr::fmadd(c.throughput, le * mis_bsdf, ls.result);
                }
            } else {
                Color3f e = m_reduced.template through<K>(c.R, c.t, c.reduced, emitter, le, emitter != nullptr);
                if (w.adjoint)
                    Lo = e * mis_bsdf;
                else
                    ls.result = dr::fmadd(e, mis_bsdf, ls.result);
            }
        }

        Bool active_next = (ls.depth + 1 < m_max_depth) && si.is_valid();
        // a directly seen emitter is a valid sample even where the path ends here
        ls.valid_ray |= ls.active && !active_next && !m_hide_emitters && si.emitter(scene) != nullptr;
        if (dr::none_or<false>(active_next)) {
            backpropagate();
            ls.active = active_next;
            return;
        }
        BSDFPtr bsdf = si.bsdf(ls.ray);
        typename Wrappers::Perturbations perturbed;
        if (!m_wrappers.empty())
            bsdf = m_wrappers.resolve(bsdf, si, ls.sampler, perturbed, active_next);

        // K == 0 with fluorescence: per lane and hero wavelength, elastic or shift
        const bool shifting = K == 0 && is_spectral_v<Spectrum> && !m_bsdfs.empty();
        fluo_detail::SurfaceShift<Float, Spectrum> shift;
        if (shifting)
            shift.choose(m_bsdfs, bsdf, si, ls.sampler, active_next, m_range_lo, m_range_hi);

        // the replay samples as the primal did, without gradients (as prb: detached
        // sampling), and differentiates the values at those samples below
        auto detached = [adjoint = w.adjoint](auto &&f) {
            dr::suspend_grad<Float> off(adjoint);
            return f();
        };

        // ---------------------- Emitter sampling ----------------------
        auto [ds, em_weight, wo, active_em] =
            detached([&] { return sample_emitter(scene, si, ls.sampler, bsdf, active_next); });
        active_em &= perturbed.keeps_side(ds.d);

        // ------ Evaluate BSDF * cos(theta) and sample direction -------
        Float sample_1 = ls.sampler->next_1d();
        Point2f sample_2 = ls.sampler->next_2d();
        auto [bsdf_val, bsdf_pdf, bs, bsdf_weight] =
            detached([&] {
                return shift.eval_pdf_sample(m_bsdfs, bsdf, bsdf_ctx, si, wo, sample_1, sample_2, true);
            });
        if (!w.adjoint) // (the replay's samples carry no gradients)
            fluo_detail::detach_moving_sample(bsdf, bsdf_ctx, si, bs, bsdf_pdf, bsdf_weight, active_next,
                                              w.differentiating);
        Float mis_em = dr::select(ds.delta, 1.f, mis_weight(ds.pdf, bsdf_pdf));
        if constexpr (dr::is_diff_v<Float>) {
            if (w.adjoint) { // values with gradients at the detached samples
                em_weight = fluo_detail::emitter_weight(scene, si, ds, em_weight, active_em);
                bsdf_val = bsdf->eval(bsdf_ctx, si, wo, active_em);
                bsdf_weight *= fluo_detail::sampled_relative(bsdf, bsdf_ctx, si, bs, active_next);
            }
        }

        if constexpr (K == 0) {
            if (shifting)
                shift.apply(m_bsdfs, bsdf, si, m_directional, wo, bs, active_next, bsdf_val, bsdf_weight);
            if (w.adjoint) {
                // next-event estimate, then the rest of the path through this weight
                Spectrum direct = dr::select(active_em, c.throughput * bsdf_val * em_weight * mis_em, 0.f);
                ls.result -= dr::detach(direct);
                Lo += direct + ls.result * fluo_detail::relative(bsdf_weight);
                backpropagate();
                c.throughput *= dr::detach(bsdf_weight);
            } else {
                if (dr::any_or<true>(active_em))
                    ls.result[active_em] =
                        dr::fmadd(c.throughput, bsdf_val * em_weight * mis_em, ls.result);
                c.throughput *= bsdf_weight;
            }
        } else {
            // the matrix throughput, diag(t)·O on first entering it
            Rows<K> R = dr::select(c.reduced, c.R, m_reduced.template output_rows<K>(c.t));

            // A fluorescent vertex's operator A = Σ w_i·M_i (+ its elastic RGB albedo as
            // band albedos when A lacks it); f·cos = A·cos θo/π (Lambertian), or a
            // direction-dependent lobe's R·A(ωo)·cos θo per direction (only in scenes that
            // hold one), its elastic part being the BSDF's own value. Towards the emitter
            // sample only R·A(ωo)·c (3 values) leaves the call.
            const bool any_em = dr::any_or<true>(active_em);
            Coeffs<K> cl = dr::zeros<Coeffs<K>>(); // the emitter sample's coefficients
            if (any_em)
                cl = m_reduced.template emitter_coefficients<K>(ds.emitter, em_weight, active_em);
            Float u_pick = m_varying ? ls.sampler->next_1d(active_next) : Float(0.f);
            auto [is_fl, native_elastic, v_fl, R_fl] = m_reduced.template vertex<K, false>(
                bsdf, si, R, cl, wo, bs.wo, bs.pdf, m_directional, u_pick, active_next);
            if (any_em) {
                // (the scalar variants form R·diag(albedo)·c only where the lane uses it)
                bool uses_red = true;
                if constexpr (!dr::is_jit_v<Float>)
                    uses_red = is_fl ? native_elastic : c.reduced;
                Color3f v_red = uses_red ? Reduced::template apply<K>(R, m_reduced.template band_albedo<K>(bsdf_val) * cl)
                                         : Color3f(0.f);
                v_fl += dr::select(native_elastic, v_red, 0.f);
                Color3f v =
                    dr::select(is_fl, v_fl, dr::select(c.reduced, v_red, c.t * bsdf_val * em_weight));
                if (w.adjoint)
                    Lo += dr::select(active_em, v * mis_em, 0.f);
                else
                    ls.result[active_em] = dr::fmadd(v, mis_em, ls.result);
            }
            m_reduced.template scatter<K>(c.R, c.t, c.reduced, R, R_fl, is_fl, native_elastic,
                                          bsdf_weight, Mask(true));
            if (w.adjoint) { // the replay carries the throughput detached, `next` keeps its gradients
                next = c;
                c.R = dr::detach(c.R);
                c.t = dr::detach(c.t);
            }
        }

        // ---------------------- BSDF sampling ----------------------
        advance(ls, si, bs);
        active_next &= perturbed.keeps_side(ls.ray.d); // a map's sample across the surface

        // -------------------- Stopping criterion ---------------------
        if constexpr (K == 0) {
            auto [rr_active, rr_scale] =
                roulette(ls, dr::max(unpolarized_spectrum(c.throughput)), active_next);
            c.throughput[rr_active] *= rr_scale;
        } else {
            Float t_max = dr::select(c.reduced, Reduced::template max_abs<K>(c.R), dr::max(c.t));
            auto [rr_active, rr_scale] = roulette(ls, t_max, active_next);
            c.R[rr_active] *= rr_scale;
            c.t[rr_active] *= rr_scale;
            if (w.adjoint) {
                next.R[rr_active] *= rr_scale;
                next.t[rr_active] *= rr_scale;
            }
        }
        ls.pi = scene->ray_intersect_preliminary(ls.ray, false, false, 0, 0, ls.active);
        if (w.adjoint) { // the path itself carries no gradients
            ls.ray = dr::detach(ls.ray);
            ls.pi = dr::detach(ls.pi);
            ls.eta = dr::detach(ls.eta);
            ls.prev_si = dr::detach(ls.prev_si);
            ls.prev_bsdf_pdf = dr::detach(ls.prev_bsdf_pdf);
        }
        if constexpr (K > 0) {
            if (w.adjoint) { // the rest of the path through this vertex's matrix throughput
                auto [coeffs, rgb] = future<K>(scene, ls, w);
                Lo += dr::select(ls.active,
                                 dr::select(c.reduced, Reduced::template apply<K>(next.R, coeffs), next.t * rgb), 0.f);
                backpropagate();
            }
        }
    }

    /// K > 0, fluo_prb's replay: the radiance still to come from `from` per unit of
    /// throughput (fluo_detail::future, this loop's continuations).
    template <size_t K>
    std::pair<Coeffs<K>, Color3f> future(const Scene *scene, const LoopState<K> &from, const Walk &w) const {
        const Walk primal{ false, false, Spectrum() };
        return fluo_detail::future<K, Coeffs<K>, Color3f>(from, Mask(dr::any(w.delta_L != 0.f)), [&](LoopState<K> &cs) {
            this->loop(cs, [&](LoopState<K> &s) { step<K>(scene, s, primal); });
        });
    }

    const Scene *m_media_warned = nullptr; ///< the scene last warned of media
};

static const bool fluo_path_jit_registered =
    (fluo_detail::register_plugin<FluoPath>("fluo_path", ObjectType::Integrator),
     fluo_detail::register_plugin<FluoPath>("fluo_prb", ObjectType::Integrator), true);

NAMESPACE_END(mitsuba)
