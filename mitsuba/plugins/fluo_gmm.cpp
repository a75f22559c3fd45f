#include "fluo_measured.h"

NAMESPACE_BEGIN(mitsuba)

/**!

.. _bsdf-fluo_gmm:

Gaussian-mixture reradiation (:monosp:`fluo_gmm`)
-------------------------------------------------

.. pluginparameters::

 * - filename
   - |string|
   - A fit file (``.gmm.json``) written by ``fluo fit-gmm X.BFC --components K -o
     X.gmm.json``: the measured diagonal, the scale S and 7 numbers per Gaussian.
     Resolved like other Mitsuba file parameters. Required.
 * - filename0, filename1, ...
   - |string|
   - Alternative to ``filename``: several files (numbered from 0, no gaps), one per
     material of an ``index`` texture.
 * - index
   - |texture|
   - Material-index texture (a one-channel ``bitmap``, a ``checkerboard``, ...): at each
     hit its ``eval_1`` value, rounded to the nearest whole number, selects
     ``filename<i>``. Every texel (bitmaps) or constituent value (textures made of
     others) must be a whole number in [0, number of files − 1], checked at load (the
     error names the texel, e.g. ``"index" = 0.5 at texel (x = 1, y = 0)``); use
     ``filter_type = nearest`` for bitmaps, since a filtered index between texels is
     rounded. Each file is loaded once; ``fluo_path`` uses the hit's material in both
     variants (in ``scalar_rgb`` each file's reduced matrix, computed once).

A diffuse (Lambertian) fluorescent material whose reradiation is a 2-D Gaussian
mixture fitted to a measured matrix (Hua et al., "Efficient Storage and Importance
Sampling for Fluorescent Reflectance", CGF 2022):

.. math::

    f(λ_i, ω_i, ω_o, λ_o) = \frac{δ(λ_i − λ_o)\,ρ(λ_i) + S \sum_k π_k \mathcal{N}((λ_i, λ_o) | μ_k, Σ_k)}{π}

restricted to the measured wavelength rectangle and λi ≤ λo; ρ is the measured
diagonal, stored as is. Wavelength shifts are importance sampled from the
conditional mixture (sec. 6.1, with the paper's slips corrected): the component is
chosen by its weight in the conditional *truncated* to the valid range, then the
wavelength by inverting that truncated normal's CDF exactly — no rejection loop,
and the returned pdf is exactly P normalised over the range. The physics lives in
the Rust core, ``core/src/models/gmm.rs``.

- ``scalar_spectral``: elastic ρ(λ)/π through the BSDF interface; reradiation
  through fluo's bispectral interface to ``fluo_path``.
- ``scalar_rgb``: the albedo under an equal-energy light, as for ``fluo_matrix``.
- Vectorised variants (``llvm_ad_*``, ``cuda_ad_*``; ``fluo_measured_jit.cpp``): the
  diagonal and the 6 numbers per component (π, μ, the symmetric Σ) are read per lane in
  float. λi | λo is sampled one component at a time: the component by its marginal
  π_k N(λo), then its normal truncated to the excitation interval (mass M_k), the
  elastic/shift choice given the component weighing the shift by S·Σ_j π_j N_j(λo)·M_k
  (unbiased over the components; two erfc per wavelength instead of two per component:
  llvm cost 1.93 -> 1.46 of ``diffuse``, same ΔE00 per sample count in ``fluo bench``);
  while the mixture's parameters carry gradients the whole truncated mixture is sampled
  as above (π_k N(λo) M_k), whose derivative estimate is less noisy. The truncated
  normal is sampled by inverting its CDF on the side of the interval where Φ is small (an erfc
  accurate to ~1e-7 relative in the tails, Φ⁻¹ by Acklam's approximation plus one Newton
  step), so no lane loses a tail to float cancellation. Where every component's weight
  underflows float (λo ~13 standard deviations from every mean) the lane takes the
  elastic event; the reradiation lost there is below float resolution of the elastic part.
  Images equal the scalar variants' within noise (``test_llvm.py``). ``mi.traverse``
  exposes the mixture as differentiable arrays ``weights`` (renormalised to sum 1 when
  used), ``means_excitation`` and ``means_emission`` (μi, μo per component, nm); in
  ``llvm_ad_spectral`` gradients reach them through the reradiation's value (the sampling
  is detached), in ``llvm_ad_rgb`` the mixture is baked into the reduced matrix per render
  and gets no gradient. An update is validated by Rust as a fit file is (a negative weight,
  a mean out of range: an error naming it, and the previous mixture stays).
  Several files selected by an ``index`` texture: every file's components are read per
  lane from arrays padded to the largest mixture (weight 0), the lane's file chosen as in
  the scalar variants (the index rounded, per hit); ``llvm_ad_rgb`` gathers each file's
  reduced matrix per lane. ``mi.traverse`` then exposes the ``index`` texture only (as the
  scalar variants), not the mixtures.

A malformed fit file (bad JSON, weights not summing to 1, a covariance that is not
symmetric positive definite, non-finite numbers) raises an error naming the field.

.. tabs::
    .. code-tab:: xml
        :name: fluo-gmm

        <bsdf type="fluo_gmm">
            <string name="filename" value="TEXTYELL.gmm.json"/>
        </bsdf>

    .. code-tab:: python

        'type': 'fluo_gmm',
        'filename': 'TEXTYELL.gmm.json'
*/
template <typename Float, typename Spectrum>
class FluoGmm final : public FluoMeasured<Float, Spectrum> {
public:
    using Base = FluoMeasured<Float, Spectrum>;
    FluoGmm(const Properties &props) : Base(props, "fluo_gmm", &fluo::gmm_new) {}
    MI_DECLARE_CLASS(FluoGmm)
};

static const bool fluo_gmm_registered =
    (fluo_detail::register_scalar_plugin<FluoGmm>("fluo_gmm", ObjectType::BSDF), true);

NAMESPACE_END(mitsuba)
