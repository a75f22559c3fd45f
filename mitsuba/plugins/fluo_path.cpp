// The fluo_path integrator: Mitsuba's path tracer extended with fluorescence. Its
// documentation is the comment below. The path loop (include/fluo/fluo_path_loop.h) is written
// once; the two transports plug into it: wavelength shifting
// (include/fluo/fluo_transport_spectral.h, also Mitsuba's plain path in either variant) and
// reduced-RGB matrix throughput (include/fluo/fluo_transport_reduced.h, scalar_rgb).
#include <mitsuba/core/properties.h>
#include <mitsuba/render/integrator.h>

#include <sstream>
#include <string>

#include "fluo_common.h"
#include "fluo_path_loop.h"
#include "fluo_transport_reduced.h"
#include "fluo_transport_spectral.h"

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
   - ``scalar_rgb`` only: transport basis for fluorescence, ``rgb`` (3 channels),
     ``xyzu`` (CIE 1931 XYZ plus a UV band) or ``x7`` (7 bands: X split in three, Y in two,
     Z, U). (Default: ``x7``: over the ``fluo bench`` scenes its mean ΔE00 against the
     spectral reference is the lowest on average and within noise of the best on each
     scene; README's generated bench table has the numbers. Its 7×7 matrices cost 392
     bytes per material and no measurable time over ``xyzu``.) Which basis when
     (``fluo-rs saturated-report`` and the second table of ``fluo bench`` measure it
     per basis): ``x7`` for saturated, narrow-band
     emitters (a pure green dye keeps its luminance within 20 % under daylight and
     incandescent light, where ``rgb`` and ``xyzu`` lose a third or more) and for
     anything excited in the UV; ``xyzu`` when materials are broad and 4×4 matrices
     matter; ``rgb`` only for scenes without UV excitation (it has no UV band: an
     optical brightener's reradiation under daylight all but vanishes) or to compare
     with a plain RGB renderer. Under narrow UV lamps every basis is coarse: one UV band
     averages a dye's absorption over 300-400 nm (a brightener under a 365 nm lamp glows
     ~5x too dark in ``xyzu``/``x7``, and not at all in ``rgb``); fluo_path warns once per
     scene when an emitter is mostly ultraviolet. Render such scenes in
     ``scalar_spectral``.
 * - method
   - |string|
   - ``scalar_rgb`` only: reduction of the reradiation, ``ours`` (dual basis, Fichet et
     al. 2024 eq. 15) or ``naive`` (eq. 7, for comparison only). (Default: ``ours``)
 * - lambda_min
   - |float|
   - Shortest excitation wavelength the integrator will ever shift to, nm, in
     [200, 360]. Spectrally defined emitters reach below the camera's 360 nm down
     to here. (Default: 300)

Unidirectional path tracing with next-event estimation and MIS, Russian roulette and
``max_depth``/``rr_depth``/``hide_emitters`` exactly as Mitsuba's ``path``, extended
with fluorescence (wavelength shifting) for fluo's bispectral BSDFs (``fluo_jung``
and the other ``fluo_*`` materials) in ``scalar_spectral``. Like ``path`` it does not
trace participating media: a scene with media gets one warning per scene pointing to
``fluo_volpath`` (which renders media, fluorescent or not).

**Vectorised variants.** In ``llvm_ad_spectral`` and ``llvm_ad_rgb`` (``fluo_path_jit.cpp``)
the same estimators run inside Mitsuba's ``dr::while_loop`` (one kernel per render): per
lane and hero wavelength the elastic/shift choice, or the 3×K matrix throughput with
Mitsuba's RGB throughput until the first fluorescent vertex, as below. The fluorescent
materials (``fluo_jung``, ``fluo_matrix``, ``fluo_gmm``) are reached through
``dr::dispatch``; their probabilities are detached, their values differentiable, so
``mi.render`` with ``params`` gives gradients of dye parameters. The scene is scanned once
per render as below. Not yet in these variants: fluorescent materials inside wrappers
(``twosided``, ``blendbsdf``, ``mask``, ``normalmap``, ``bumpmap``: refused at render
start with an error).

**Simulate only what the scene calls for.** At the start of each render the scene is
scanned once: the fluorescent BSDFs (those implementing fluo's bispectral interface
and re-emitting at all) and the spectral range of every emitter's radiance texture.
Light exists only where emitters emit or fluorescence re-emits, so excitation is
sampled only inside R = [max(emitters' min, lambda_min), max(emitters' max,
emission max)]. A material whose absorption band misses R is treated as a plain
BSDF. With nothing left, this integrator runs exactly Mitsuba's ``path`` (the same
code, the same random numbers: identical images), in both variants.

**Fluorescence in RGB (reduced transport).** In ``scalar_rgb`` a scene with fluorescent
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
weight makes up for it, so only the variance changes. That is why ``w_f`` may come
from a table: for materials whose ``w_f`` does not depend on ωi, it is tabulated over
λo once per scene, exact at 1 nm nodes, interpolated between two positive nodes and
exact elsewhere; ``fluo::shift``.) After the choice the vertex is an
ordinary (wavelength-changing) BSDF: next-event estimation and BSDF sampling estimate
the incident radiance L(λi, ω) with the usual MIS weights, which do not depend on
wavelength. Each hero wavelength is an independent estimator of its camera
wavelength's radiance, so the film's wavelength weights stay valid.

Spatially varying fluorescence (``fluo_jung`` with a ``color`` texture) is looked up
per vertex through the bispectral interface's ``fluorescence_at(si)``: each vertex
uses its own texel's model and intersects its excitation band with R.

Fluorescent materials may be wrapped in ``twosided``, ``blendbsdf`` and ``mask``
(nested too): at each vertex the integrator resolves the wrapper to the BSDF that acts
there — ``twosided``: the front or back child, with the local frame mirrored for the
back side exactly as ``twosided`` does; ``blendbsdf``: child 1 with probability w(si),
else child 0; ``mask``: the nested BSDF with probability opacity(si), else a null
(pass-through) interaction, as ``mask`` samples it; ``normalmap`` and ``bumpmap`` (in
the scalar variants): the nested BSDF in the perturbed shading frame, which every lobe
of the vertex then uses (elastic and fluorescent), with the adapters' rule that a
direction on different sides of the two frames carries nothing — and treats that child
as an unwrapped material. The selections are unbiased: renders equal the wrapper's within
noise. Any other BSDF around a fluorescent one is refused with an error at render start
(the first access the integrator has to the scene) rather than rendered without its
fluorescence. Mitsuba's own integrators
(``path``, ...) render only the elastic part of fluorescent materials, and say so once
per scene.

.. tabs::
    .. code-tab:: xml

        <integrator type="fluo_path">
            <integer name="max_depth" value="8"/>
        </integrator>
*/
template <typename Float, typename Spectrum>
class FluoPath final : public FluoPathLoop<Float, Spectrum> {
public:
    MI_IMPORT_BASE(FluoPathLoop, m_max_depth, m_rr_depth)
    MI_IMPORT_TYPES(Scene, Sensor, Sampler, Medium)
    using Spectral = SpectralTransport<Float, Spectrum>;
    using Reduced = ReducedTransport<Float, Spectrum>;

    static constexpr const char *Plugin = "fluo_path";

    FluoPath(const Properties &props)
        : Base(props), m_lambda_min(fluo_detail::lambda_min_of(Plugin, props)),
          m_reduced(Plugin, fluo_detail::get_string(props, "basis", "x7"),
                    fluo_detail::get_string(props, "method", "ours")) {}

    using Base::render;
    TensorXf render(Scene *scene, Sensor *sensor, UInt32 seed, uint32_t spp, bool develop,
                    bool evaluate) override {
        prepare(scene);
        return Base::render(scene, sensor, seed, spp, develop, evaluate);
    }

    std::pair<Spectrum, Bool> sample(const Scene *scene, Sampler *sampler,
                                     const RayDifferential3f &ray, const Medium * /* medium */,
                                     Float * /* aovs */, Bool active) const override {
        if constexpr (is_rgb_v<Spectrum>) {
            if (m_reduced.active()) {
                typename Reduced::Path path(m_reduced);
                return Base::trace(scene, sampler, ray, active, path);
            }
        }
        typename Spectral::Path path(m_spectral);
        return Base::trace(scene, sampler, ray, active, path);
    }

    std::string to_string() const override {
        std::ostringstream oss;
        fluo::Range range = m_spectral.range();
        oss << "FluoPath[" << std::endl
            << "  max_depth = " << m_max_depth << "," << std::endl
            << "  rr_depth = " << m_rr_depth << "," << std::endl
            << "  lambda_min = " << m_lambda_min << "," << std::endl
            << "  basis = " << m_reduced.basis_name() << " (K = " << m_reduced.bands() << ")," << std::endl
            << "  fluorescent_bsdfs = " << (is_rgb_v<Spectrum> ? m_reduced.size() : m_spectral.size()) << ","
            << std::endl
            << "  excitation_range = [" << range.lo << ", " << range.hi << "]" << std::endl
            << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(FluoPath)

private:
    /// Scan the scene once per render for the variant's transport: fluorescent BSDFs,
    /// their wrappers, and what the emitters emit.
    void prepare(Scene *scene) {
        fluo_detail::warn_if_media(Plugin, scene, m_media_warned);
        Base::m_wrappers.clear();
        if constexpr (is_rgb_v<Spectrum>)
            m_reduced.prepare(scene, Base::m_wrappers);
        else
            m_spectral.prepare(scene, Base::m_wrappers, m_lambda_min, Plugin);
    }

    const Scene *m_media_warned = nullptr; ///< the scene last warned of media
    double m_lambda_min;
    Reduced m_reduced;   ///< scalar_rgb with fluorescent materials (the basis is checked in both variants)
    Spectral m_spectral; ///< scalar_spectral, and scalar_rgb without fluorescent materials
};

static const bool fluo_path_registered =
    (fluo_detail::register_scalar_plugin<FluoPath>("fluo_path", ObjectType::Integrator), true);

NAMESPACE_END(mitsuba)
