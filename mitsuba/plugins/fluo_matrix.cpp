#include "fluo_measured.h"

NAMESPACE_BEGIN(mitsuba)

/**!

.. _bsdf-fluo_matrix:

Measured reradiation matrix (:monosp:`fluo_matrix`)
---------------------------------------------------

.. pluginparameters::

 * - filename
   - |string|
   - A measured reradiation (Donaldson) matrix: a Labsphere BFC text file (``.bfc``),
     a CSV matrix (``.csv``, header ``lambda_o\lambda_i,300,...``) or a bispectral
     Spectral OpenEXR file (``.exr``, channels ``T.<λ>nm`` and ``T.<λi>nm.<λo>nm``).
     Resolved like other Mitsuba file parameters (relative to the scene). Required.
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

A diffuse (Lambertian) fluorescent material that renders a measured matrix D(λo, λi)
exactly as tabulated:

.. math::

    f(λ_i, ω_i, ω_o, λ_o) = \frac{δ(λ_i − λ_o)\,ρ(λ_i) + P(λ_i, λ_o)}{π}

with ρ the matrix diagonal (linearly interpolated, held constant beyond its ends) and
P the entries above the diagonal divided by the emission band width (energy per nm),
interpolated bilinearly in λi and λo and zero for λi > λo. Before use, entries below
the diagonal and negative entries are set to zero (measurement noise; Hua et al.
2022, sec. 5.1). Wavelength shifts are importance sampled exactly from tabulated
cumulative integrals of the rows (λi given λo) and columns (λo given λi). The
physics lives in the Rust core, ``core/src/models/matrix.rs``.

- ``scalar_spectral``: the BSDF interface serves the elastic part ρ(λ)/π; the
  reradiation is served through fluo's bispectral interface to ``fluo_path``
  (under Mitsuba's ``path`` the absorbed light is lost).
- ``scalar_rgb``: the albedo under an equal-energy light, ρ(λ) + ∫ P(λi, λ) dλi over
  360–830 nm, in Mitsuba's sRGB convention.
- Vectorised variants (``llvm_ad_rgb``, ``llvm_ad_spectral``, and the cuda ones from the
  same code; ``fluo_measured_jit.cpp``): Rust loads and validates the file and hands over
  the diagonal, P and the running integrals of its rows; per lane the shim finds cells by
  binary search and inverts the row CDF with the same quadratic root, in float (the tables
  are f64 in Rust: a float CDF resolves about 1e-7 of a row's mass, far below the noise).
  In ``llvm_ad_rgb`` ``fluo_path`` uses the same reduced matrix as ``scalar_rgb``. Images
  equal the scalar variants' within noise (``test_llvm.py``). Several files selected by
  an ``index`` texture: the files' grids and tables are concatenated and each lane reads
  its file's (the index rounded per hit, as the scalar variants; a binary search runs over
  the longest grid with each lane clamped to its own), and ``llvm_ad_rgb`` gathers each
  file's reduced matrix per lane.

A malformed file (truncated, a NaN, a wrong header, a wavelength off its grid) raises
an error naming the file and the line and column.

.. tabs::
    .. code-tab:: xml
        :name: fluo-matrix

        <bsdf type="fluo_matrix">
            <string name="filename" value="TEXTYELL.BFC"/>
        </bsdf>

    .. code-tab:: xml
        :name: fluo-matrix-index

        <bsdf type="fluo_matrix">
            <string name="filename0" value="TEXTYELL.BFC"/>
            <string name="filename1" value="CIBA12.BFC"/>
            <texture type="bitmap" name="index">
                <string name="filename" value="label_index.png"/>
                <boolean name="raw" value="true"/>
                <string name="filter_type" value="nearest"/>
            </texture>
        </bsdf>

    .. code-tab:: python

        'type': 'fluo_matrix',
        'filename': 'postit_yellow.csv'
*/
template <typename Float, typename Spectrum>
class FluoMatrix final : public FluoMeasured<Float, Spectrum> {
public:
    using Base = FluoMeasured<Float, Spectrum>;
    FluoMatrix(const Properties &props) : Base(props, "fluo_matrix", &fluo::matrix_new) {}
    MI_DECLARE_CLASS(FluoMatrix)
};

static const bool fluo_matrix_registered =
    (fluo_detail::register_scalar_plugin<FluoMatrix>("fluo_matrix", ObjectType::BSDF), true);

NAMESPACE_END(mitsuba)
