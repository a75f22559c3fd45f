// fluo_matrix and fluo_gmm, one class template (FluoMeasured) for every variant they serve
// (the documentation below).
//
// Rust loads and validates the file and hands over its tables (fluo::measured_tables): the
// diagonal, and the matrix's P and row integrals or the mixture's components. Per lane the
// plugin evaluates the same functions with Dr.Jit types in float:
// - ρ(λ): the diagonal, linear between nodes, constant beyond its ends.
// - fluo_matrix: λi | λo by inverting the bilinear interpolant's row CDF exactly (binary
//   search over the row integrals, then the cell's quadratic root), as matrix.rs does.
// - fluo_gmm: λi | λo from the mixture of truncated conditional normals: the whole
//   truncated mixture while the mixture carries gradients, else
//   one component at a time: the component by its marginal π_k N(λo | μo, σoo) (a rough
//   exp, corrected in the estimate), then its
//   normal truncated to the excitation interval, the elastic/shift choice given the
//   component weighing the shift by that component's share (gmm_shift and gmm_shift_split
//   say why both are unbiased). A truncated normal is sampled by inverting its CDF (Φ from
//   an erfc accurate to ~1e-7 relative in the tails, Φ⁻¹ by Acklam's approximation and one
//   Newton step) on the side of the interval where Φ is small. Lanes where every
//   component's marginal underflows float (the given λo ~13 standard deviations from every
//   component) take the elastic event: their reradiation is then below float resolution of
//   the elastic part.
// The RGB variants use the reduced matrix Rust computes for the transport basis.
#include <mitsuba/core/fresolver.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/render/bsdf.h>

#include <cmath>
#include <optional>
#include <string>
#include <vector>

#include "fluo_common.h"
#include "fluo_bispectral.h"
#include "fluo_lambertian.h"
#include "fluo_measured_files.h"

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
     rounded. Each file is loaded once; ``fluo_path`` uses the hit's material in every
     variant (in the RGB variants each file's reduced matrix, computed once).

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

- Spectral variants: the BSDF interface serves the elastic part ρ(λ)/π; the
  reradiation is served through fluo's bispectral interface to ``fluo_path``
  (under Mitsuba's ``path`` the absorbed light is lost).
- RGB variants: the albedo under an equal-energy light, ρ(λ) + ∫ P(λi, λ) dλi over
  360–830 nm, in Mitsuba's sRGB convention; under ``fluo_path``, the reduced matrix Rust
  computes for the transport basis.

In every variant it serves (``scalar_*``, ``llvm_ad_*``, ``cuda_ad_*``; one class,
``fluo_measured.cpp``) Rust loads and validates the file and hands over the diagonal, P
and the running integrals of its rows; per lane the plugin finds cells by binary search
and inverts the row CDF with the same quadratic root, in float (the tables are f64 in
Rust: a float CDF resolves about 1e-7 of a row's mass, far below the noise). No variant
calls Rust per vertex. Several files selected by an ``index`` texture: the files' grids
and tables are concatenated and each lane reads its file's (the index rounded per hit; a
binary search runs over the longest grid with each lane clamped to its own), and in the
RGB variants each file's reduced matrix is gathered per lane.

**Parameters and gradients.** ``mi.traverse`` exposes P at the matrix's nodes as the
array ``reradiation`` (nm⁻¹, λo rows of λi entries; with several files, each file's matrix
in file order). An update is validated by Rust (one entry per node, each finite, ≥ 0 and,
times its emission band width, within a file's bound of 1e3: an error naming it, and the
previous matrices stay) and the sampling tables are baked again. It is differentiable in every AD
variant (``llvm_ad_*``, ``cuda_ad_*``): in the spectral ones through the value of the
shift at the sampled wavelength (the sampling and its mass detached); in the RGB ones,
where P is baked into the reduced matrix per render, through that matrix's derivative,
exactly: the reduction is linear in P, so Rust's Jacobian of the reduction (one K×K
matrix per node) turns P's change into the change of each of the operator's entries
once per render (only while P carries gradients; the operator is then a kernel input;
several files: each file's change, gathered per lane by its file).
Changing the diagonal or the grids needs a new file.

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
     rounded. Each file is loaded once; ``fluo_path`` uses the hit's material in every
     variant (in the RGB variants each file's reduced matrix, computed once).

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

- Spectral variants: elastic ρ(λ)/π through the BSDF interface; reradiation
  through fluo's bispectral interface to ``fluo_path``.
- RGB variants: the albedo under an equal-energy light, as for ``fluo_matrix``; under
  ``fluo_path``, the reduced matrix Rust computes for the transport basis.

In every variant it serves (one class, ``fluo_measured.cpp``) the diagonal and the 6
numbers per component (π, μ, the symmetric Σ) are read per lane in float; no variant
calls Rust per vertex. While the mixture's parameters carry gradients (``llvm_ad_*``,
``cuda_ad_*``), λi | λo is sampled from the whole truncated
mixture as above (the component by π_k N(λo) M_k), whose derivative estimate is less
noisy. Otherwise it is sampled one component at a time: the component by its marginal
π_k N(λo) (with a 4 % approximation of exp, one exact exp for the drawn component), then
its normal truncated to the excitation interval (mass M_k), the elastic/shift choice
given the component weighing the shift by S·Σ_j π_j Ñ_j(λo)·M_k·N_k/Ñ_k (Ñ: the
approximation; unbiased over the components; two erfc per wavelength instead of two per
component: llvm cost 1.93 -> 1.46 of ``diffuse``, same ΔE00 per sample count in ``fluo
bench``).
The truncated normal is sampled by inverting its CDF on the side of the interval where Φ
is small (an erfc accurate to ~1e-7 relative in the tails, Φ⁻¹ by Acklam's approximation
plus one Newton step), so no lane loses a tail to float cancellation. Where every
component's weight underflows float (λo ~13 standard deviations from every mean) the lane
takes the elastic event; the reradiation lost there is below float resolution of the
elastic part. ``mi.traverse`` exposes the mixture as arrays ``weights`` (renormalised to
sum 1 when used), ``means_excitation`` and ``means_emission`` (μi, μo per component, nm).
An update is validated by Rust as a fit file is (a negative weight, a mean out of range:
an error naming it, and the previous mixture stays). Several files selected by an
``index`` texture: every file's components are read per lane from arrays padded to the
largest mixture (weight 0), the lane's file chosen by the index rounded per hit, and in
the RGB variants each file's reduced matrix is gathered per lane; ``mi.traverse`` then
exposes the ``index`` texture and the mixtures' arrays, [file][component] with each
file's padded to the largest mixture: an update keeps the padding (weight and means 0; a
padded entry set to anything else is refused, naming the file) and Rust validates each
file's components as one file's.

**Gradients** (``llvm_ad_*``, ``cuda_ad_*``). ``weights``, ``means_excitation`` and
``means_emission`` are differentiable: in the spectral variants gradients reach them
through the reradiation's value (the sampling is detached); in the RGB variants, where the
mixture is baked into the reduced matrix per render, through that matrix's derivatives
(``fluo_path``): along each renormalised weight the difference of the reductions at a
0.1 % step of it (exact: the reduced operator is linear in the weights), along each mean
central differences (0.25 nm) of the reductions, computed at a render's start
only while the arrays carry gradients (3 × components K×K matrices; the operator then
becomes a kernel input, not literals). With several files, per file: each derivative a
table of the files' K×K matrices along their component k (jit_reduced_table_derivatives),
a lane adding its file's times its own θ − detach(θ).

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
class FluoMeasured : public BSDF<Float, Spectrum>, public fluo_detail::BispectralBSDF<Float, Spectrum> {
public:
    MI_IMPORT_BASE(BSDF, m_flags, m_components)
    MI_IMPORT_TYPES(Texture)
    using WMask = dr::mask_t<UnpolarizedSpectrum>;
    using FloatStorage = DynamicBuffer<Float>;
    using Factory = typename fluo_detail::MeasuredFiles<Float, Spectrum>::Factory;
    using fluo_detail::BispectralBSDF<Float, Spectrum>::MaxTerms;
    using Choice = typename fluo_detail::BispectralBSDF<Float, Spectrum>::Choice;

    FluoMeasured(const Properties &props, const char *plugin, Factory factory) : Base(props), m_plugin(plugin) {
        fluo_detail::MeasuredFiles<Float, Spectrum> files(props, plugin, factory);
        m_keys = std::move(files.keys);
        m_filenames = std::move(files.paths);
        m_models = std::move(files.models);
        m_index = files.index;
        load_tables();
        update_rgb();
        m_flags = BSDFFlags::DiffuseReflection | BSDFFlags::FrontSide;
        m_components.push_back(m_flags);
    }

    void traverse(TraversalCallback *cb) override {
        m_record.arm(this);
        Base::traverse(cb);
        if (m_index)
            cb->put("index", m_index, ParamFlags::NonDifferentiable);
        if (m_gmm) { // the mixtures' weights and means ([file][component], padded)
            // (RGB: baked into the reduced matrices, updated by re-baking; gradients through
            // the operator's derivative matrices: jit_reduced_derivatives, several files
            // jit_reduced_table_derivatives)
            cb->put("weights", m_weights, ParamFlags::Differentiable);
            cb->put("means_excitation", m_means_i, ParamFlags::Differentiable);
            cb->put("means_emission", m_means_o, ParamFlags::Differentiable);
        } else // P at its nodes (nm⁻¹, [λo][λi]; several files: theirs in file order)
            cb->put("reradiation", m_p, ParamFlags::Differentiable);
    }

    /// fluo_gmm: Rust validates the updated mixture (weights renormalised to sum 1, means
    /// within range), fluo_matrix its reradiation P (finite, ≥ 0, one value per node), and
    /// bakes the RGB parts, reduced matrices and sampling tables again; a refused update
    /// puts every traversed value back (fluo_detail::UpdateRecord), so the material keeps
    /// working.
    void parameters_changed(const std::vector<std::string> &keys) override {
        m_record.update(this, [&] {
            if (m_index) // a changed index map is validated again
                fluo_detail::MeasuredFiles<Float, Spectrum>::check_index(m_plugin, m_index.get(), m_models.size());
            std::vector<rust::Box<fluo::MeasuredModel>> models; // (all validated before any is kept)
            if (!m_gmm) { // Rust validates each file's matrix and bakes its rows' integrals again
                std::vector<double> p = host(m_p);
                size_t total = m_file_off.back() + m_file_nodes.back();
                if (p.size() != total)
                    Throw("%s: \"reradiation\" must keep its %zu entries (one per node of %s), %zu given",
                          m_plugin, total, m_models.size() > 1 ? "every file's matrix, in file order" : "the matrix",
                          p.size());
                std::vector<float> rcdf;
                for (size_t f = 0; f < m_models.size(); ++f) {
                    models.push_back(fluo_detail::rust_call(m_plugin, [&] {
                        return fluo::matrix_updated(*m_models[f],
                                                    rust::Slice<const double>(p.data() + m_file_off[f], m_file_nodes[f]));
                    }));
                    rust::Vec<double> r = fluo::measured_tables(*models.back()).row_cdf;
                    rcdf.insert(rcdf.end(), r.begin(), r.end());
                }
                load_tables(p, rcdf);
            } else {
                bool mixture = keys.empty() || std::any_of(keys.begin(), keys.end(), [](const std::string &k) {
                                   return k == "weights" || k == "means_excitation" || k == "means_emission";
                               });
                if (!mixture) // (an index update alone: the mixtures stay as Rust holds them)
                    return;
                std::vector<double> w = host(m_weights), mi = host(m_means_i), mo = host(m_means_o);
                size_t total = m_n_comps * m_models.size();
                if (w.size() != total || mi.size() != total || mo.size() != total)
                    Throw("%s: \"weights\", \"means_excitation\" and \"means_emission\" must keep %zu entries%s",
                          m_plugin, total,
                          m_models.size() > 1 ? " ([file][component], each file's padded to the largest mixture)" : "");
                for (size_t f = 0; f < m_models.size(); ++f) {
                    size_t o = f * m_n_comps, k = m_file_comps[f];
                    for (size_t c = k; c < m_n_comps; ++c)
                        if (w[o + c] != 0.0 || mi[o + c] != 0.0 || mo[o + c] != 0.0)
                            Throw("%s: \"weights\"/\"means_excitation\"/\"means_emission\" entry %zu pads \"%s\" "
                                  "(%zu components of %zu) and must stay 0",
                                  m_plugin, o + c, m_keys[f], k, m_n_comps);
                    auto slice = [&](const std::vector<double> &v) {
                        return rust::Slice<const double>(v.data() + o, k);
                    };
                    models.push_back(fluo_detail::rust_call(
                        m_plugin, [&] { return fluo::gmm_updated(*m_models[f], slice(w), slice(mi), slice(mo)); }));
                }
            }
            m_models = std::move(models);
            m_table_key.clear(); // (the files' reduced operators: reduced again)
            update_rgb();
        });
        fix_mixture(); // (the values accepted)
        Base::parameters_changed(keys);
    }

    FLUO_LAMBERTIAN_BSDF_METHODS(albedo(si, active), this->warn_if_unmanaged(m_plugin))

    // ------------------------------------------------ fluo_path's interface (fluo_bispectral.h)
    /// Whether any file re-emits.
    bool jit_fluorescent() const override {
        return std::any_of(m_models.begin(), m_models.end(),
                           [](const auto &m) { return fluo::measured_is_fluorescent(*m); });
    }
    /// The files' emission ranges' hull.
    fluo::Range jit_emission_range() const override {
        std::vector<const fluo::Fluorescence *> f;
        for (const auto &m : m_models)
            f.push_back(fluo::measured_is_fluorescent(*m) ? &fluo::measured_fluorescence(*m) : nullptr);
        return fluo_detail::emission_hull(f);
    }
    fluo::Range jit_excitation_range() const override {
        if (m_index)
            return { 0.0, 1e30 };
        return fluo::fluo_excitation_range(fluo::measured_fluorescence(*m_models[0]));
    }
    /// The whole operator ρ·diag + P, reduced by Rust. Several files: none here
    /// (jit_reduced_table holds one per file).
    bool jit_reduced_matrices(const fluo::TransportBasis &transport,
                              std::array<std::vector<double>, MaxTerms> &m) const override {
        if (m_index)
            return reduced_table(transport).second;
        auto reduced = fluo::reduced_new(fluo::measured_fluorescence(*m_models[0]), transport);
        if (!fluo::reduced_lambertian(*reduced, rust::Slice<double>(m[0].data(), m[0].size())))
            Throw("%s: no Lambertian reduced operator", m_plugin);
        return fluo::reduced_includes_elastic(*reduced);
    }
    std::array<Float, MaxTerms> jit_reduced_weights() const override {
        return { Float(m_index ? 0.f : 1.f), Float(0.f), Float(0.f) };
    }
    bool jit_uniform() const override { return !m_index; }

    /// fluo_gmm (one file) in RGB with gradients on its mixture: A = E + S·Σ_k π̂_k R_k (π̂ the
    /// renormalised weights, R_k component k's reduced unit normal). Along π̂_k: S·R_k − S·Σ_j
    /// π̂_j R_j, exactly (A(w + ε e_k) − A(w))·(W + ε)/ε for weights w of sum W (the common
    /// part adds nothing: the π̂_k's derivatives sum to 0; a small ε keeps the mixture within
    /// the bound Rust holds a fit's peak to, which a component alone may exceed). Along a mean: central differences of the reductions
    /// (0.25 nm; one-sided where Rust refuses the step, out of the measured rectangle). In
    /// the order of jit_reduced_derivative_weights: weights, means_excitation,
    /// means_emission, each per component, for the arrays that carry gradients.
    ///
    /// fluo_matrix in RGB with gradients on its reradiation P: a file's reduced operator is
    /// linear in P's nodes, A = E + Σ_n p_n·J_n (J from Rust, fluo::matrix_reduced_jacobian),
    /// so the change of each entry of A, δA_e = Σ_n J_n[e]·(p_n − detach(p_n)), is summed once
    /// per render for every file at once (table_derivatives; zero in value, P's derivative) and
    /// added to that entry: one unit matrix per entry some J_n reaches, its weight a value of
    /// the kernel (one file) or gathered per lane by its file (several).
    size_t jit_reduced_derivatives(const fluo::TransportBasis &transport,
                                   std::vector<std::vector<double>> &d) const override {
        if (m_index && m_gmm)
            return 0;
        if (!m_gmm) {
            m_delta.clear();
            m_delta_entries.clear();
            if (!dr::grad_enabled(m_p))
                return 0;
            size_t n = table_derivatives(transport, d);
            if (!m_index) // one file: its entries as values of the kernel, not gathered per lane
                for (uint32_t e : m_delta_entries)
                    m_delta.push_back(fluo_detail::fetch<Float>(m_delta_table, UInt32(e)));
            return n;
        }
        if (!mixture_gradients())
            return 0;
        file_derivatives(*m_models[0], { host(m_weights), host(m_means_i), host(m_means_o) }, transport, d,
                         m_keys[0]);
        return d.size();
    }
    /// The mixture's arrays, in the derivatives' order.
    std::array<const FloatStorage *, 3> mixture_arrays() const { return { &m_weights, &m_means_i, &m_means_o }; }
    /// One file's reduced operator's derivatives along its mixture `x` (weights, μi, μo, its
    /// own components), appended to `d`: per array that carries gradients, per component.
    void file_derivatives(const fluo::MeasuredModel &model, const std::array<std::vector<double>, 3> &x,
                          const fluo::TransportBasis &transport, std::vector<std::vector<double>> &d,
                          const std::string &file) const {
        size_t n = x[0].size(), kk = fluo::transport_size(transport) * fluo::transport_size(transport);
        auto reduce = [&](const std::array<std::vector<double>, 3> &y) -> std::optional<std::vector<double>> {
            auto slice = [](const std::vector<double> &v) { return rust::Slice<const double>(v.data(), v.size()); };
            std::vector<double> out(kk);
            try {
                auto updated = fluo::gmm_updated(model, slice(y[0]), slice(y[1]), slice(y[2]));
                auto reduced = fluo::reduced_new(fluo::measured_fluorescence(*updated), transport);
                if (!fluo::reduced_lambertian(*reduced, rust::Slice<double>(out.data(), kk)))
                    return std::nullopt;
            } catch (const std::exception &) {
                return std::nullopt; // a mean stepped out of range
            }
            return out;
        };
        std::optional<std::vector<double>> at_x; // A at the current mixture (the weights' differences)
        double total = 0.0; // W, and the weights' step ε
        for (double v : x[0])
            total += v;
        const double eps = 1e-3 * total;
        for (size_t a = 0; a < 3; ++a) {
            if (!dr::grad_enabled(*mixture_arrays()[a]))
                continue;
            for (size_t c = 0; c < n; ++c) {
                std::optional<std::vector<double>> dc;
                if (a == 0) { // along π̂_c: (A(w + ε e_c) − A(w))·(W + ε)/ε, W = Σ w (A is linear in π̂)
                    std::array<std::vector<double>, 3> y = x;
                    y[0][c] += eps;
                    if (!at_x)
                        at_x = reduce(x);
                    std::optional<std::vector<double>> up = reduce(y);
                    if (up && at_x)
                        for (size_t j = 0; j < kk; ++j)
                            (*up)[j] = ((*up)[j] - (*at_x)[j]) * (total + eps) / eps;
                    dc = at_x ? up : std::nullopt;
                } else {
                    dc = fluo_detail::central_difference(0.25, [&](double delta) {
                        std::array<std::vector<double>, 3> y = x;
                        y[a][c] += delta;
                        return reduce(y);
                    });
                }
                if (!dc)
                    Throw("%s: no derivative of \"%s\"'s reduced operator along component %zu's %s", m_plugin,
                          file, c, a == 0 ? "weight" : a == 1 ? "excitation mean" : "emission mean");
                d.push_back(std::move(*dc));
            }
        }
    }
    /// θ − detach(θ) per derivative matrix: the renormalised weights π̂_k, the means
    /// (fluo_gmm); the entries' δA (fluo_matrix).
    std::vector<Float> jit_reduced_derivative_weights(const SurfaceInteraction3f &si, Mask active) const override {
        if (!m_gmm && m_index) { // the lane's file's δA entries
            std::vector<Float> w;
            UInt32 base = material(si, active) * (uint32_t) m_delta_kk;
            for (uint32_t e : m_delta_entries)
                w.push_back(fluo_detail::fetch<Float>(m_delta_table, base + e, active));
            return w;
        }
        return !m_gmm ? m_delta : mixture_deltas(UInt32(0), active);
    }
    /// θ − detach(θ) of file `mat`'s mixture (its renormalised weights π̂_k, its means), per
    /// array that carries gradients, per component slot.
    std::vector<Float> mixture_deltas(const UInt32 &mat, const Mask &active) const {
        std::vector<Float> w;
        UInt32 base = mat * (uint32_t) m_n_comps;
        if (dr::grad_enabled(m_weights)) {
            fluo_detail::Scratch<Float> p = weights(mat, active);
            for (size_t c = 0; c < m_n_comps; ++c)
                w.push_back(p[c] - dr::detach(p[c]));
        }
        for (const FloatStorage *means : { &m_means_i, &m_means_o })
            if (dr::grad_enabled(*means))
                for (size_t c = 0; c < m_n_comps; ++c) {
                    Float m = fluo_detail::fetch<Float>(*means, base + (uint32_t) c, active);
                    w.push_back(m - dr::detach(m));
                }
        return w;
    }
    /// Several files: each one's reduced operator, selected per lane by the index texture.
    size_t jit_reduced_table(const fluo::TransportBasis &transport, std::vector<double> &m) const override {
        if (!m_index)
            return 0;
        m = reduced_table(transport).first;
        return m_models.size();
    }
    std::pair<UInt32, Float> jit_reduced_select(const SurfaceInteraction3f &si, Mask active) const override {
        return { material(si, active), Float(1.f) };
    }
    /// fluo_gmm, several files, in RGB with gradients on the mixtures: per array that carries
    /// them and component slot k a table of every file's ∂A/∂θ_k, as one file's
    /// (jit_reduced_derivatives: the weights' exact difference, the means' central ones),
    /// zero for a file with fewer components.
    size_t jit_reduced_table_derivatives(const fluo::TransportBasis &transport,
                                         std::vector<double> &d) const override {
        m_mix_d = 0;
        if (!m_gmm || !m_index || !mixture_gradients())
            return 0;
        size_t n = m_n_comps, nf = m_models.size(), kk = fluo::transport_size(transport);
        kk *= kk;
        std::array<std::vector<double>, 3> x = { host(m_weights), host(m_means_i), host(m_means_o) };
        size_t arrays = 0; // those that carry gradients
        for (const FloatStorage *a : mixture_arrays())
            arrays += dr::grad_enabled(*a) ? 1 : 0;
        d.assign(arrays * n * nf * kk, 0.0); // [array][slot][file][K][K]
        for (size_t f = 0; f < nf; ++f) {
            size_t k = m_file_comps[f];
            std::array<std::vector<double>, 3> own;
            for (size_t a = 0; a < 3; ++a)
                own[a].assign(x[a].begin() + (std::ptrdiff_t) (f * n), x[a].begin() + (std::ptrdiff_t) (f * n + k));
            std::vector<std::vector<double>> df; // [array][own component]
            file_derivatives(*m_models[f], own, transport, df, m_keys[f]);
            for (size_t g = 0; g < arrays; ++g)
                for (size_t c = 0; c < k; ++c)
                    std::copy(df[g * k + c].begin(), df[g * k + c].end(), d.begin() + ((g * n + c) * nf + f) * kk);
        }
        m_mix_d = (uint32_t) (arrays * n);
        return m_mix_d;
    }
    std::vector<Float> jit_reduced_select_derivatives(const SurfaceInteraction3f &si, Mask active) const override {
        // (m_mix_d: as counted when the render began)
        return m_mix_d == 0 ? std::vector<Float>() : mixture_deltas(material(si, active), active);
    }

    UnpolarizedSpectrum jit_elastic_albedo(const SurfaceInteraction3f &si, Mask active) const override {
        UInt32 mat = material(si, active);
        if constexpr (is_rgb_v<Spectrum>) {
            return dr::gather<Color3f>(m_rgb_elastic, mat, active); // (3 values per file)
        } else {
            return UnpolarizedSpectrum(reflectance(m_gd.at(mat, active), si.wavelengths, active));
        }
    }

    Choice jit_choose(const SurfaceInteraction3f &si, const Wavelength &u1, const Wavelength &u2, double range_lo,
                      double range_hi, Mask active) const override {
        if constexpr (dr::is_jit_v<Float>)
            return choose(si, u1, u2, range_lo, range_hi, active);
        else
            return choose_inlined(si, u1, u2, range_lo, range_hi, active);
    }
    /// (scalar variants: with every call inlined, Dr.Jit's exp/log among them, which g++
    /// leaves out of line: the fluo_gmm vertex 1.42 -> 1.34 of diffuse's)
    __attribute__((flatten)) Choice choose_inlined(const SurfaceInteraction3f &si, const Wavelength &u1,
                                                   const Wavelength &u2, double range_lo, double range_hi,
                                                   Mask active) const {
        return choose(si, u1, u2, range_lo, range_hi, active);
    }
    Choice choose(const SurfaceInteraction3f &si, const Wavelength &u1, const Wavelength &u2, double range_lo,
                  double range_hi, Mask active) const {
        const Wavelength &lambda_o = si.wavelengths;
        if constexpr (!is_spectral_v<Spectrum>) {
            return this->elastic_only(lambda_o);
        } else {
            UInt32 mat = material(si, active);
            File file = file_at(mat, active);
            UnpolarizedSpectrum albedo = jit_elastic_albedo(si, active), we = dr::maximum(albedo, 0.f);
            Mixture own;
            const Mixture &mix = m_gmm ? mixture_at(mat, active, own) : own;
            // Per hero wavelength the excitation interval [a, b] (λi ≤ λo) and its mass; the
            // shift's value and pdf once sampled with u2 (the four wavelengths at once:
            // fluo_gmm's exp/erfc and fluo_matrix's cells in packets).
            Wavelength a = dr::maximum((float) range_lo, file.rect[0]),
                       b = dr::minimum(dr::minimum((float) range_hi, lambda_o), file.rect[1]);
            WMask ok = WMask(active) && b > a && lambda_o >= file.rect[2] && lambda_o <= file.rect[3];
            // (scalar variants draw λi only where the shift is taken: `takes`; fluo_matrix:
            // whether the lights reach below every file's first λi node, so that a is that node)
            auto takes = [&](const Wavelength &m) {
                return dr::any(fluo_detail::ShiftChoice<Wavelength>(we, m, u1, active).shifted);
            };
            const bool from_start = !m_gmm && range_lo <= (double) m_lambda_i_min;
            auto [mass, x, value] = m_gmm ? gmm_shift(mix, file, lambda_o, a, b, u2, ok, takes)
                                          : matrix_shift(file, lambda_o, a, b, u2, ok, from_start, takes);
            fluo_detail::ShiftChoice<UnpolarizedSpectrum> choice(we, mass, u1, active);
            UnpolarizedSpectrum scale = choice.weight(dr::detach(value) / mass, u1);
            // π·f_fl(λi, λo) = P(λi, λo)
            return { dr::select(choice.shifted, x, lambda_o), scale, choice.shifted,
                     dr::select(choice.shifted, value, 0.f), UInt32(0), albedo };
        }
    }

    std::string to_string() const override {
        std::ostringstream oss;
        oss << this->class_name() << "[" << std::endl;
        for (size_t i = 0; i < m_models.size(); ++i)
            oss << "  " << m_keys[i] << " = \"" << m_filenames[i] << "\"," << std::endl
                << "  model = " << std::string(fluo::measured_to_string(*m_models[i])) << "," << std::endl;
        if (m_index)
            oss << "  index = " << string::indent(m_index) << "," << std::endl;
        oss << "  evaluation = tables per lane" << std::endl << "]";
        return oss.str();
    }

protected:
    using UInt32Storage = DynamicBuffer<UInt32>;

    /// The wavelength grids of one axis (the diagonal's, λi's or λo's) of every file.
    using Grids = fluo_detail::LaneGridSet<Float>;

    /// What a lane's file holds beyond its diagonal: its λi and λo grids and P's offset
    /// (fluo_matrix), its scale (fluo_gmm) and where P can be non-zero:
    /// [λi_min, λi_max, λo_min, λo_max] (the matrix's grids, the mixture's measured rectangle).
    struct File {
        typename Grids::At gi, go;
        UInt32 p_off;
        Float scale;
        std::array<Float, 4> rect;
    };
    File file_at(const UInt32 &mat, const Mask &active) const {
        File f;
        if (!m_gmm) {
            f.gi = m_gi.at(mat, active);
            f.go = m_go.at(mat, active);
            f.p_off = m_index ? fluo_detail::fetch<UInt32>(m_p_off, mat, active) : UInt32(0);
        }
        for (size_t i = 0; i < 4; ++i)
            f.rect[i] = m_index ? fluo_detail::fetch<Float>(m_d_rect, mat * 4 + (uint32_t) i, active) : Float(m_rect[i]);
        f.scale = m_index ? fluo_detail::fetch<Float>(m_d_scale, mat, active) : Float(m_scale[0]);
        return f;
    }

    /// The file at si: 0 without an index texture, else the texture's value (its own
    /// eval_1: to_uv, filter) rounded to the nearest whole number, within range (0 where
    /// not finite).
    UInt32 material(const SurfaceInteraction3f &si, const Mask &active) const {
        if (!m_index)
            return UInt32(0);
        Float v = m_index->eval_1(si, active);
        // (halves away from zero, as std::lround: not dr::round's ties to even)
        Float r = dr::clip(dr::floor(v + .5f), 0.f, (float) (m_models.size() - 1));
        return UInt32(dr::select(dr::isfinite(v), r, 0.f));
    }

    /// A mixture component's fixed numbers (its covariance): −1/(2σoo), 1/√(2π σoo),
    /// σio/σoo and the conditional standard deviation √(det Σ/σoo). Its weight and mean
    /// are differentiable arrays (m_weights, m_means_i, m_means_o).
    struct Comp {
        float half_inv_var_o, norm, slope, cond_sd;
    };

    /// Every file's tables from Rust, concatenated (fluo::measured_tables): the diagonals;
    /// fluo_matrix: the λi, λo grids, P and its rows' running integrals; fluo_gmm: the
    /// components, padded to the largest mixture with weight 0.
    void load_tables() {
        std::vector<float> diag, p, rcdf, rect, scale;
        std::vector<uint32_t> p_off;
        std::vector<std::vector<Comp>> comps;
        for (const auto &model : m_models) {
            fluo::MeasuredTables t = fluo::measured_tables(*model);
            m_gmm = std::string(t.kind) == "gmm";
            m_gd.add(t.diagonal_nm);
            diag.insert(diag.end(), t.diagonal.begin(), t.diagonal.end());
            if (m_gmm) {
                scale.push_back((float) t.scale);
                rect.insert(rect.end(), t.rect.begin(), t.rect.end());
                comps.emplace_back();
                for (size_t c = 0; c + 6 <= t.components.size(); c += 6) {
                    const double *v = t.components.data() + c;
                    double det = v[3] * v[5] - v[4] * v[4];
                    // N(λo | μo, σoo) and the conditional λi | λo: mean μi + σio/σoo (λo − μo),
                    // standard deviation √(det/σoo).
                    comps.back().push_back({ (float) (-0.5 / v[5]),
                                             (float) (1.0 / std::sqrt(2.0 * dr::Pi<double> * v[5])),
                                             (float) (v[4] / v[5]), (float) std::sqrt(det / v[5]) });
                }
            } else {
                m_gi.add(t.lambda_i);
                m_go.add(t.lambda_o);
                p_off.push_back((uint32_t) p.size());
                m_file_off.push_back(p.size());
                m_file_nodes.push_back(t.p.size());
                p.insert(p.end(), t.p.begin(), t.p.end());
                rcdf.insert(rcdf.end(), t.row_cdf.begin(), t.row_cdf.end());
                scale.push_back(0.f);
                for (auto &v : { t.lambda_i.front(), t.lambda_i.back(), t.lambda_o.front(), t.lambda_o.back() })
                    rect.push_back((float) v);
            }
        }
        m_gd.upload();
        m_diag = dr::load<FloatStorage>(diag.data(), diag.size());
        if (!m_gmm) {
            m_gi.upload();
            m_go.upload();
            m_p = dr::load<FloatStorage>(p.data(), p.size());
            load_tables(p, rcdf);
            m_p_off = dr::load<UInt32Storage>(p_off.data(), p_off.size());
        } else {
            // [file][component], padded: weight 0 (never drawn, no value), σ = 1
            m_n_comps = 0;
            m_file_comps.clear();
            for (const auto &c : comps) {
                m_n_comps = std::max(m_n_comps, c.size());
                m_file_comps.push_back(c.size());
            }
            m_comps.assign(m_n_comps * m_models.size(), Comp{ -0.5f, 0.f, 0.f, 1.f });
            for (size_t f = 0; f < comps.size(); ++f)
                std::copy(comps[f].begin(), comps[f].end(), m_comps.begin() + (std::ptrdiff_t) (f * m_n_comps));
            std::vector<float> cols[4];
            for (const Comp &c : m_comps)
                for (size_t i = 0; i < 4; ++i)
                    cols[i].push_back((&c.half_inv_var_o)[i]);
            for (size_t i = 0; i < 4; ++i)
                m_d_comp[i] = dr::load<FloatStorage>(cols[i].data(), cols[i].size());
            load_mixture();
            fix_mixture();
        }
        std::copy(rect.begin(), rect.begin() + 4, m_rect.begin());
        m_lambda_i_min = dr::Infinity<float>;
        for (size_t f = 0; f < rect.size(); f += 4)
            m_lambda_i_min = std::min(m_lambda_i_min, rect[f]);
        m_scale = scale;
        m_d_rect = dr::load<FloatStorage>(rect.data(), rect.size());
        m_d_scale = dr::load<FloatStorage>(scale.data(), scale.size());
    }

    /// fluo_gmm: the differentiable weights and means from Rust's components ([file][component]
    /// as m_comps, padded with weight 0).
    void load_mixture() {
        std::vector<float> weight(m_comps.size(), 0.f), mean_i(m_comps.size(), 0.f), mean_o(m_comps.size(), 0.f);
        for (size_t f = 0; f < m_models.size(); ++f) {
            fluo::MeasuredTables t = fluo::measured_tables(*m_models[f]);
            for (size_t c = 0, k = f * m_n_comps; c + 6 <= t.components.size(); c += 6, ++k) {
                weight[k] = (float) t.components[c];
                mean_i[k] = (float) t.components[c + 1];
                mean_o[k] = (float) t.components[c + 2];
            }
        }
        m_weights = dr::load<FloatStorage>(weight.data(), weight.size());
        m_means_i = dr::load<FloatStorage>(mean_i.data(), mean_i.size());
        m_means_o = dr::load<FloatStorage>(mean_o.data(), mean_o.size());
    }

    /// Several files in RGB: each file's reduced operator ([file][K][K]) and whether they
    /// include the elastic part (every measured file's does: its diagonal is known
    /// spectrally; a mix would be an error). Reduced once per basis (fluo_path asks for both
    /// halves at each render's start).
    const std::pair<std::vector<double>, bool> &reduced_table(const fluo::TransportBasis &transport) const {
        std::string key(fluo::transport_label(transport));
        if (key == m_table_key)
            return m_table;
        size_t kk = fluo::transport_size(transport) * fluo::transport_size(transport);
        std::vector<double> m(kk * m_models.size(), 0.0);
        bool full = true;
        for (size_t f = 0; f < m_models.size(); ++f) {
            auto reduced = fluo::reduced_new(fluo::measured_fluorescence(*m_models[f]), transport);
            bool includes = fluo::reduced_includes_elastic(*reduced);
            if (f > 0 && includes != full)
                Throw("%s: \"%s\" and \"%s\" reduce differently (one with its elastic part, one without)",
                      m_plugin, m_keys[0], m_keys[f]);
            full = includes;
            if (!fluo::reduced_lambertian(*reduced, rust::Slice<double>(m.data() + f * kk, kk)))
                Throw("%s: no Lambertian reduced operator for \"%s\"", m_plugin, m_keys[f]);
        }
        m_table = { std::move(m), full };
        m_table_key = key;
        return m_table;
    }

    /// RGB variants: each file's albedos under equal-energy light, from Rust.
    /// jit_reduced_derivatives of P: [file][entry] sums of J_f[n][e]·δp_f[n]
    /// over each file's nodes (padded to the largest file with zero weights), one unit
    /// matrix per entry some file's Jacobian reaches.
    size_t table_derivatives(const fluo::TransportBasis &transport, std::vector<std::vector<double>> &d) const {
        size_t files = m_models.size(), kk = fluo::transport_size(transport) * fluo::transport_size(transport);
        size_t widest = *std::max_element(m_file_nodes.begin(), m_file_nodes.end());
        std::vector<float> jac(files * kk * widest, 0.f);
        std::vector<uint32_t> node(files * kk * widest, 0);
        std::vector<bool> reached(kk, false);
        for (size_t f = 0; f < files; ++f) {
            rust::Vec<double> j = fluo::matrix_reduced_jacobian(*m_models[f], transport);
            if (j.size() != m_file_nodes[f] * kk)
                Throw("%s: the reduction's derivative of file %zu has %zu entries, %zu nodes × %zu expected", m_plugin,
                      f, j.size(), m_file_nodes[f], kk);
            for (size_t e = 0; e < kk; ++e)
                for (size_t n = 0; n < m_file_nodes[f]; ++n) {
                    size_t at = (f * kk + e) * widest + n;
                    jac[at] = (float) j[n * kk + e];
                    node[at] = (uint32_t) (m_file_off[f] + n);
                    reached[e] = reached[e] || jac[at] != 0.f;
                }
        }
        if constexpr (dr::is_diff_v<Float>) {
            FloatStorage delta = m_p - dr::detach(m_p);
            m_delta_table = dr::block_sum(dr::load<FloatStorage>(jac.data(), jac.size()) *
                                              dr::gather<FloatStorage>(delta, dr::load<UInt32Storage>(node.data(), node.size())),
                                          widest);
        }
        m_delta_kk = kk;
        for (size_t e = 0; e < kk; ++e)
            if (reached[e]) {
                m_delta_entries.push_back((uint32_t) e);
                d.emplace_back(kk, 0.0);
                d.back()[e] = 1.0;
            }
        return d.size();
    }

    void update_rgb() {
        if constexpr (is_rgb_v<Spectrum>) {
            std::vector<float> albedo, elastic;
            for (const auto &m : m_models) {
                fluo::Rgb a = fluo::measured_rgb_albedo(*m), e = fluo::measured_rgb_elastic(*m);
                for (double v : { a.r, a.g, a.b })
                    albedo.push_back((float) v);
                for (double v : { e.r, e.g, e.b })
                    elastic.push_back(std::clamp((float) v, 0.f, 1.f));
            }
            m_rgb_albedo = dr::load<FloatStorage>(albedo.data(), albedo.size());
            m_rgb_elastic = dr::load<FloatStorage>(elastic.data(), elastic.size());
        }
    }

    /// ρ(λ) of a lane's file: linear between the diagonal's nodes, constant beyond its ends
    /// (0 for λ not finite).
    /// (the four hero wavelengths at once: in the scalar variants, in SIMD registers)
    template <typename Value>
    Value reflectance(const typename Grids::At &gd, const Value &lambda, const Mask &active) const {
        dr::mask_t<Value> on = dr::mask_t<Value>(active) && dr::isfinite(lambda);
        Value x = dr::clip(lambda, gd.lo, gd.hi);
        auto [j, x0, x1] = m_gd.cell(gd, x, on);
        Value t = dr::clip((x - x0) / (x1 - x0), 0.f, 1.f);
        dr::uint32_array_t<Value> i = gd.off + j;
        Value v = dr::lerp(fluo_detail::fetch_each<Value>(m_diag, i, on),
                           fluo_detail::fetch_each<Value>(m_diag, i + 1, on), t);
        return dr::select(on, v, 0.f);
    }

    /// The albedo served to Mitsuba: the diagonal (spectral), or in RGB the albedo under
    /// equal-energy light (diagonal plus reradiation).
    UnpolarizedSpectrum albedo(const SurfaceInteraction3f &si, Mask active) const {
        if constexpr (is_rgb_v<Spectrum>)
            return dr::gather<Color3f>(m_rgb_albedo, material(si, active), active);
        else
            return jit_elastic_albedo(si, active);
    }

    /// fluo_matrix: given λo, the row slice P(·, λo) = (1 − t)·row_j + t·row_{j+1} over λi;
    /// its mass on [a, b], a λi sampled ∝ the slice there with u, and P at that λi. The
    /// slice is sampled as the mixture it is: row j or j+1 with probability ∝ its weight
    /// times its mass on [a, b], then λi ∝ that row by inverting its CDF exactly (the last
    /// node whose running integral is ≤ the target, then the cell's quadratic root in the
    /// cancellation-free form of matrix.rs). The density is the slice's own, P/mass.
    /// Value: a Float, or the packet of a lane's four hero wavelengths (in the scalar variants
    /// their arithmetic in SIMD registers).
    template <typename Value, typename Takes>
    std::tuple<Value, Value, Value> matrix_shift(const File &file, const Value &lambda_o, const Value &a,
                                                 const Value &b, const Value &u, const dr::mask_t<Value> &ok,
                                                 bool from_start, const Takes &takes) const {
        using UIntV = dr::uint32_array_t<Value>;
        using MaskV = dr::mask_t<Value>;
        const typename Grids::At &gi = file.gi, &go = file.go;
        Value lo = dr::clip(lambda_o, go.lo, go.hi);
        auto [j, o0, o1] = m_go.cell(go, lo, ok);
        Value t = dr::clip((lo - o0) / (o1 - o0), 0.f, 1.f);
        UIntV r0 = file.p_off + j * gi.n, r1 = r0 + gi.n, last(gi.n - 1);
        // (the sampling and the mass from P detached, m_cells; the value attached when P
        // carries gradients)
        auto c = [&](const UIntV &r, const UIntV &k) { return fluo_detail::fetch_each<Value>(m_rcdf, r + k, ok); };
        // a row's integral at node k and P at nodes k and k + 1, in one read
        auto cell = [&](const UIntV &r, const UIntV &k) { return fluo_detail::fetch_packet<4, 3, Value>(m_cells, r + k, ok); };
        // ∫ from λi_0 to x of each row.
        auto cdf = [&](const Value &x) {
            auto [k, x0, x1] = m_gi.cell(gi, x, ok);
            Value s = dr::clip((x - x0) / (x1 - x0), 0.f, 1.f), half = .5f * (x - x0);
            auto [c0, f0, f1] = cell(r0, k);
            auto [c1, g0, g1] = cell(r1, k);
            return std::make_tuple(c0 + half * (f0 + dr::lerp(f0, f1, s)), c1 + half * (g0 + dr::lerp(g0, g1, s)), k);
        };
        Value a_ = dr::select(ok, a, gi.lo), b_ = dr::select(ok, b, gi.lo);
        // (`from_start`: a is every lane's first λi node, where both rows' integrals are 0)
        auto [ca0, ca1, k_lo] = from_start ? std::make_tuple(Value(0.f), Value(0.f), UIntV(0)) : cdf(a_);
        auto [cb0, cb1, k_hi] = cdf(b_);
        Value m0 = (1.f - t) * dr::maximum(cb0 - ca0, 0.f), m1 = t * dr::maximum(cb1 - ca1, 0.f);
        Value mass = dr::select(ok, m0 + m1, 0.f);
        if constexpr (!dr::is_jit_v<Float>)
            if (!takes(mass))
                return { mass, lambda_o, 0.f };
        // The row, and u rescaled within its share.
        Value split = u * mass;
        MaskV second = (split >= m0 && m1 > 0.f) || !(m0 > 0.f);
        UIntV r = dr::select(second, r1, r0);
        Value m_row = dr::select(second, cb1 - ca1, cb0 - ca0);
        Value u_row = dr::clip(dr::select(second, (split - m0) / m1, split / m0), 0.f, 1.f);
        Value target = dr::select(second, ca1, ca0) + u_row * dr::maximum(m_row, 0.f);
        // (over the longest λi grid, each lane's row clamped to its own last node)
        UIntV k = dr::binary_search<UIntV>(1, m_gi.n_max - 1,
                                           [&](const UIntV &i) { return c(r, dr::minimum(i, last)) <= target; }) -
                  1;
        k = dr::clip(k, k_lo, k_hi);
        Mask uniform = gi.step > 0.f;
        MaskV nodes = ok && !MaskV(uniform);
        Value x0 = dr::select(uniform, dr::fmadd(Value(k), gi.step, gi.lo),
                              fluo_detail::fetch_each<Value>(m_gi.nodes, gi.off + k, nodes));
        Value x1 = dr::select(uniform, x0 + gi.step, fluo_detail::fetch_each<Value>(m_gi.nodes, gi.off + k + 1, nodes));
        Value h = x1 - x0;
        auto [c0, f0, f1] = cell(r0, k);
        auto [c1, g0, g1] = cell(r1, k);
        Value e0 = dr::select(second, g0, f0), e1 = dr::select(second, g1, f1);
        Value step = fluo_detail::linear_cell_inverse(e0, e1, h, target - dr::select(second, c1, c0));
        Value x = dr::clip(x0 + step, dr::maximum(a_, x0), dr::minimum(b_, x1));
        Value s = dr::clip((x - x0) / h, 0.f, 1.f);
        Value value = dr::lerp(dr::lerp(f0, f1, s), dr::lerp(g0, g1, s), t);
        if (dr::grad_enabled(m_p)) {
            auto pa = [&](const UIntV &r, const UIntV &k) { return fluo_detail::fetch_each<Value>(m_p, r + k, ok); };
            value = dr::lerp(dr::lerp(pa(r0, k), pa(r0, k + 1), s), dr::lerp(pa(r1, k), pa(r1, k + 1), s), t);
        }
        return { mass, x, dr::select(ok, value, 0.f) };
    }

    /// erfc(x) to ~1.2e-7 relative for every x (Numerical Recipes' Chebyshev fit; Dr.Jit's
    /// erf alone loses the tails to cancellation in float).
    template <typename Value> static Value erfc(const Value &x) {
        Value z = dr::abs(x), t = dr::rcp(dr::fmadd(.5f, z, 1.f));
        Value p = 0.17087277f;
        for (float c : { -0.82215223f, 1.48851587f, -1.13520398f, 0.27886807f, -0.18628806f, 0.09678418f,
                         0.37409196f, 1.00002368f, -1.26551223f })
            p = dr::fmadd(p, t, c);
        Value r = t * dr::exp(dr::fmadd(-z, z, p));
        return dr::select(x >= 0.f, r, 2.f - r);
    }

    /// exp(x) for x ≤ 0 to ~4 % (Schraudolph's: x/ln 2 written into a float's exponent and
    /// mantissa; 0 below −87): weights of a choice whose estimate divides by them.
    template <typename Value> static Value rough_exp(const Value &x) {
        Value v = dr::reinterpret_array<Value>(dr::int32_array_t<Value>(dr::fmadd(x, 12102203.f, 1064986823.f)));
        return dr::select(x > -87.f, v, 0.f);
    }

    /// Φ(z), the standard normal CDF, accurate in relative terms for z < 0.
    template <typename Value> static Value phi_cdf(const Value &z) { return .5f * erfc(-z * dr::InvSqrtTwo<float>); }

    /// Φ⁻¹(p) for p ∈ (0, 1): Acklam's rational approximation, then (`Refine`) one Newton
    /// step. Without it, evaluated in float, |Δz| ≤ 2e-4 over p ∈ [1e-30, 0.98] (measured
    /// against Python's NormalDist; 0.004 nm where σ = 20 nm): enough to place a λi whose
    /// weight does not depend on it (gmm_shift_split), and 2 exp + 1 erfc cheaper (the
    /// llvm_ad_spectral vertex: 1.43 -> 1.34 of diffuse's).
    template <bool Refine, typename Value> static Value phi_inv(const Value &p_) {
        Value p = dr::clip(p_, 1e-37f, 1.f - 6e-8f);
        // Lower tail (p < 0.02425; the upper tail by symmetry): ±n(q)/d(q), q = √(−2 log p);
        // central region: c·n(c²)/d(c²), c = p − ½. One rational per lane, its coefficients
        // chosen per lane (the tail's denominator has a degree less: a leading 0).
        dr::mask_t<Value> upper = p > 1.f - 0.02425f, in_tail = p < 0.02425f || upper;
        Value c = p - .5f;
        Value x = dr::select(in_tail, dr::sqrt(-2.f * dr::log(dr::select(upper, 1.f - p, p))), c * c);
        static constexpr float Num[2][6] = { { -3.969683028665376e+01f, 2.209460984245205e+02f, -2.759285104469687e+02f,
                                               1.383577518672690e+02f, -3.066479806614716e+01f, 2.506628277459239e+00f },
                                             { -7.784894002430293e-03f, -3.223964580411365e-01f, -2.400758277161838e+00f,
                                               -2.549732539343734e+00f, 4.374664141464968e+00f, 2.938163982698783e+00f } },
                               Den[2][6] = { { -5.447609879822406e+01f, 1.615858368580409e+02f, -1.556989798598866e+02f,
                                               6.680131188771972e+01f, -1.328068155288572e+01f, 1.f },
                                             { 0.f, 7.784695709041462e-03f, 3.224671290700398e-01f,
                                               2.445134137142996e+00f, 3.754408661907416e+00f, 1.f } };
        Value n = 0.f, d = 0.f;
        for (size_t i = 0; i < 6; ++i) {
            n = dr::fmadd(n, x, dr::select(in_tail, Value(Num[1][i]), Value(Num[0][i])));
            d = dr::fmadd(d, x, dr::select(in_tail, Value(Den[1][i]), Value(Den[0][i])));
        }
        Value z = dr::select(in_tail, dr::select(upper, Value(-1.f), Value(1.f)), c) * n / d;
        if constexpr (!Refine)
            return z;
        // Newton on Φ(z) = p (relative to the smaller tail).
        Value density = dr::exp(-.5f * z * z) * dr::InvSqrtTwoPi<float>;
        Value err = dr::select(z > 0.f, (1.f - p) - phi_cdf(-z), phi_cdf(z) - p); // Φ(z) − p
        Value step = err / density;
        return dr::select(density > 0.f && dr::isfinite(step), z - step, z);
    }

    /// fluo_gmm: the conditional mixture given λo on [a, b] (see the file's header): its
    /// mass S Σ_k π_k N(λo) M_k, a λi sampled from it with u, and P(λi, λo) there. The
    /// weights (renormalised) and means are read from their arrays: the mass and the sample
    /// are detached, P carries their gradients.
    /// The mixture's weights (renormalised, times the normalisation of N(λo)) and means,
    /// read once per vertex from the differentiable arrays.
    /// With several files, a lane's file's components ([file][component], padded with weight
    /// 0): their fixed numbers too are read per lane (one file: constants of the kernel).
    struct Mixture {
        fluo_detail::Scratch<Float> weight, mu_i, mu_o, half_inv_var_o, slope, cond_sd;
    };
    Mixture mixture(const UInt32 &mat, const Mask &active) const {
        size_t n = m_n_comps;
        Mixture m;
        for (auto *v : { &m.weight, &m.mu_i, &m.mu_o, &m.half_inv_var_o, &m.slope, &m.cond_sd })
            v->resize(n);
        UInt32 base = mat * (uint32_t) n;
        fluo_detail::Scratch<Float> norm(n);
        m.weight = weights(mat, active);
        for (size_t k = 0; k < n; ++k) {
            UInt32 index = m_index ? base + (uint32_t) k : UInt32((uint32_t) k);
            m.mu_i[k] = fluo_detail::fetch<Float>(m_means_i, index, active);
            m.mu_o[k] = fluo_detail::fetch<Float>(m_means_o, index, active);
            const Comp &c = m_comps[k];
            Float *fixed[4] = { &m.half_inv_var_o[k], &norm[k], &m.slope[k], &m.cond_sd[k] };
            for (size_t i = 0; i < 4; ++i)
                *fixed[i] = m_index ? fluo_detail::fetch<Float>(m_d_comp[i], index, active) : Float((&c.half_inv_var_o)[i]);
        }
        for (size_t k = 0; k < n; ++k)
            m.weight[k] *= norm[k];
        return m;
    }

    /// The lane's mixture: with one file and no gradients the same at every vertex, formed
    /// once (fix_mixture: at load and on each accepted update; its reading per vertex was 7 %
    /// of a scalar fluo_gmm render; JIT variants: evaluated values the kernels read, not
    /// literals, so an update reuses them), else read into `scratch`.
    const Mixture &mixture_at(const UInt32 &mat, const Mask &active, Mixture &scratch) const {
        if (m_fixed_mixture && !mixture_gradients())
            return *m_fixed_mixture;
        scratch = mixture(mat, active);
        return scratch;
    }
    void fix_mixture() {
        m_fixed_mixture.reset();
        if (!m_gmm || m_index)
            return;
        dr::suspend_grad<Float> detached;
        Mixture m = mixture(UInt32(0), Mask(true));
        if constexpr (dr::is_jit_v<Float>)
            for (size_t k = 0; k < m_n_comps; ++k)
                dr::make_opaque(m.weight[k], m.mu_i[k], m.mu_o[k]);
        m_fixed_mixture = std::move(m);
    }

    /// The mixture's weights at a lane's file renormalised to sum 1 (differentiable): taken
    /// relative to the largest (a constant: detached) before they are summed, so that tiny
    /// ones (1e-30) normalise without overflowing 1/wsum² in the gradient.
    fluo_detail::Scratch<Float> weights(const UInt32 &mat, const Mask &active) const {
        size_t n = m_n_comps;
        fluo_detail::Scratch<Float> w(n);
        UInt32 base = mat * (uint32_t) n;
        Float wmax = 0.f, wsum = 0.f;
        for (size_t k = 0; k < n; ++k) {
            UInt32 index = m_index ? base + (uint32_t) k : UInt32((uint32_t) k);
            w[k] = fluo_detail::fetch<Float>(m_weights, index, active);
            // a file's padding (several files: its norm is 0) takes no part in the gradient,
            // so an optimiser keeps it at 0 (which an update requires)
            if (m_index && dr::grad_enabled(w[k]))
                w[k] = dr::select(fluo_detail::fetch<Float>(m_d_comp[1], index, active) > 0.f, w[k], dr::detach(w[k]));
            wmax = dr::maximum(wmax, dr::detach(w[k]));
        }
        Float rel = dr::select(wmax > 0.f, dr::rcp(wmax), 0.f);
        for (size_t k = 0; k < n; ++k) {
            w[k] *= rel;
            wsum += w[k];
        }
        Float inv_wsum = dr::rcp(wsum);
        for (size_t k = 0; k < n; ++k)
            w[k] *= inv_wsum;
        return w;
    }

    bool mixture_gradients() const {
        return dr::grad_enabled(m_weights) || dr::grad_enabled(m_means_i) || dr::grad_enabled(m_means_o);
    }

    /// The rows' integrals at their nodes (m_rcdf) and, per entry of P, the cell that
    /// matrix_shift reads at once (m_cells): [C(r, k), P(r, k), P(r, k + 1), 0] (P past the
    /// last entry 0: a cell's k + 1 is a node of its own row), detached.
    template <typename P> void load_tables(const std::vector<P> &p, const std::vector<float> &rcdf) {
        m_rcdf = dr::load<FloatStorage>(rcdf.data(), rcdf.size());
        std::vector<float> cells(4 * p.size(), 0.f);
        for (size_t i = 0; i < p.size(); ++i)
            for (auto [c, v] : { std::pair{ 0, (double) rcdf[i] }, std::pair{ 1, (double) p[i] },
                                 std::pair{ 2, i + 1 < p.size() ? (double) p[i + 1] : 0.0 } })
                cells[4 * i + c] = (float) v;
        m_cells = dr::load<FloatStorage>(cells.data(), cells.size());
    }

    /// A differentiable array's values on the host (detached).
    static std::vector<double> host(const FloatStorage &v) {
        std::vector<float> f = fluo_detail::host_lanes(v, dr::width(v));
        return std::vector<double>(f.begin(), f.end());
    }

    /// fluo_gmm's shift given λo on [a, b]: (the shift's weight in the elastic/shift choice,
    /// λi, the value whose ratio to that weight is the density of λi). Without gradients
    /// through the mixture one component at a time (gmm_shift_split: two erfc per
    /// wavelength); with them the whole truncated mixture (gmm_shift_mixture), whose
    /// estimate of d/dθ has the image's variance (measured: the split estimator's weights
    /// gradient scattered 2x more per seed). Both are unbiased (test_llvm.py test09, test12);
    /// the whole mixture costs ~3x the split one per vertex in the scalar variants (measured:
    /// 4.8x diffuse's vertex against ~1.6x).
    template <typename Value, typename Takes>
    std::tuple<Value, Value, Value> gmm_shift(const Mixture &mix, const File &file, const Value &lambda_o,
                                              const Value &a, const Value &b, const Value &u,
                                              const dr::mask_t<Value> &ok, const Takes &takes) const {
        return mixture_gradients() ? gmm_shift_mixture(mix, file, lambda_o, a, b, u, ok)
                                   : gmm_shift_split(mix, file, lambda_o, a, b, u, ok, takes);
    }

    /// fluo_gmm, given λo on [a, b]: P(λi, λo) = S Σ_k π_k N(λo | μo_k, σoo_k) N(λi | m_k, s_k²)
    /// = Σ_k f_k(λi) (the conditional form of each bivariate component). A component k is
    /// drawn ∝ its marginal π_k N(λo) (probability p_k), then λi from its normal truncated to
    /// [a, b] (density q_k = N/M_k, M_k its mass there) with u rescaled; the shift's value
    /// and density are f_k(λi) and p_k q_k(λi), whose ratio is S·W·M_k (W = Σ_k π_k N(λo)):
    /// that is also the weight the elastic/shift choice uses given k. Conditioned on k the
    /// vertex estimates the elastic part plus f_k/p_k, so over k it is unbiased for the
    /// elastic part plus ∫P, with one truncated mass (two erfc) per wavelength instead of
    /// one per component. The component is drawn with rough marginals π_k Ñ(λo) (rough_exp,
    /// summing to W̃; one exact exp, of the drawn k, instead of one per component), so its
    /// estimate is f_k/(p_k q_k) = S·W̃·M_k·N/Ñ: unbiased as before, whatever the error of Ñ
    /// (it moves the choice by a few percent, not the mean). Returns (that estimate, λi,
    /// the estimate): value/weight = 1, f_k is never evaluated. Renders without gradients
    /// take this path (gmm_shift).
    template <typename Value, typename Takes>
    std::tuple<Value, Value, Value> gmm_shift_split(const Mixture &mix, const File &file, const Value &lambda_o,
                                              const Value &a, const Value &b, const Value &u,
                                              const dr::mask_t<Value> &ok, const Takes &takes) const {
        size_t n = m_n_comps;
        fluo_detail::Scratch<Value> marginal(n);
        Value total = 0.f;
        for (size_t k = 0; k < n; ++k) {
            Value d = lambda_o - mix.mu_o[k];
            marginal[k] = dr::detach(mix.weight[k]) * rough_exp(dr::detach(mix.half_inv_var_o[k]) * d * d);
            total += marginal[k];
        }
        // The component: the first k with u·W̃ < Σ_{≤k} marginal (the last one with a
        // positive marginal if rounding leaves none); u rescaled within it.
        Value target = u * total, run = 0.f, crun = 0.f, cslope = 0.f, cmu_i = 0.f, cmu_o = 0.f, csd = 1.f, cw = 0.f,
              cweight = 0.f, chalf = 0.f;
        dr::mask_t<Value> done = !ok || !(total > 0.f);
        for (size_t k = 0; k < n; ++k) {
            const Value &w = marginal[k];
            dr::mask_t<Value> take = !done && w > 0.f;
            crun = dr::select(take, run, crun);
            cmu_i = dr::select(take, Value(mix.mu_i[k]), cmu_i);
            cmu_o = dr::select(take, Value(mix.mu_o[k]), cmu_o);
            cslope = dr::select(take, Value(mix.slope[k]), cslope);
            csd = dr::select(take, Value(mix.cond_sd[k]), csd);
            cw = dr::select(take, w, cw);
            cweight = dr::select(take, Value(mix.weight[k]), cweight);
            chalf = dr::select(take, Value(mix.half_inv_var_o[k]), chalf);
            done |= take && target < run + w;
            run += w;
        }
        Value cu = dr::clip((target - crun) / dr::maximum(cw, dr::Smallest<float>), 0.f, 1.f);
        Value mean = dr::fmadd(cslope, lambda_o - cmu_o, cmu_i), mean_d = dr::detach(mean), inv_sd = dr::rcp(csd);
        Value d = lambda_o - dr::detach(cmu_o);
        total *= dr::detach(cweight) * dr::exp(dr::detach(chalf) * d * d) / dr::maximum(cw, dr::Smallest<float>);
        Value lo = (a - mean_d) * inv_sd, hi = (b - mean_d) * inv_sd;
        // On the side where Φ is small: an interval above the mean is mirrored.
        dr::mask_t<Value> mirror = lo > 0.f;
        Value za = dr::select(mirror, -hi, lo), zb = dr::select(mirror, -lo, hi);
        Value pa = phi_cdf(za), pb = phi_cdf(zb), mass_k = dr::maximum(pb - pa, 0.f);
        Value estimate = file.scale * total * mass_k;
        dr::mask_t<Value> good = ok && total > 0.f && mass_k > 0.f;
        estimate = dr::select(good, estimate, 0.f);
        if constexpr (!dr::is_jit_v<Value>)
            if (!takes(estimate))
                return { estimate, lambda_o, estimate };
        Value z = phi_inv<false>(dr::fmadd(cu, pb - pa, pa));
        // (clamped to the interval in the mirrored coordinate)
        Value x = dr::clip(mean_d + csd * dr::select(mirror, -z, z), a, b);
        return { estimate, x, estimate };
    }

    /// fluo_gmm, given λo on [a, b], the whole truncated mixture: the component by its share
    /// π_k N(λo) M_k, then its truncated normal; returns (S Σ_k π_k N(λo) M_k, λi, P(λi, λo)),
    /// P differentiable in the weights and means (gmm_shift says when it is used).
    template <typename Value>
    std::tuple<Value, Value, Value> gmm_shift_mixture(const Mixture &mix, const File &file, const Value &lambda_o,
                                              const Value &a, const Value &b, const Value &u,
                                              const dr::mask_t<Value> &ok) const {
        size_t n = m_n_comps;
        fluo_detail::Scratch<Value> w(n), za(n), zb(n), pa(n), pb(n), mean(n), marginal(n);
        fluo_detail::Scratch<dr::mask_t<Value>> mirror(n);
        Value total = 0.f;
        for (size_t k = 0; k < n; ++k) {
            Value d = lambda_o - mix.mu_o[k];
            marginal[k] = mix.weight[k] * dr::exp(mix.half_inv_var_o[k] * d * d);
            mean[k] = dr::fmadd(mix.slope[k], d, mix.mu_i[k]);
            Value mean_d = dr::detach(mean[k]), inv_sd = dr::rcp(mix.cond_sd[k]);
            Value lo = (a - mean_d) * inv_sd, hi = (b - mean_d) * inv_sd;
            // On the side where Φ is small: an interval above the mean is mirrored.
            mirror[k] = lo > 0.f;
            za[k] = dr::select(mirror[k], -hi, lo);
            zb[k] = dr::select(mirror[k], -lo, hi);
            pa[k] = phi_cdf(za[k]);
            pb[k] = phi_cdf(zb[k]);
            w[k] = dr::select(ok, dr::detach(marginal[k]) * dr::maximum(pb[k] - pa[k], 0.f), 0.f);
            total += w[k];
        }
        // The component: the first k with u·total < Σ_{≤k} w (the last one with w > 0 if
        // rounding leaves none); u rescaled within it.
        Value target = u * total, run = 0.f, ca = 0.f, cb = 0.f, cmean = 0.f, csd = 1.f, crun = 0.f, cw = 0.f;
        dr::mask_t<Value> done = !ok || !(total > 0.f), cmirror = false;
        for (size_t k = 0; k < n; ++k) {
            dr::mask_t<Value> take = !done && w[k] > 0.f;
            ca = dr::select(take, pa[k], ca);
            cb = dr::select(take, pb[k], cb);
            cmean = dr::select(take, dr::detach(mean[k]), cmean);
            csd = dr::select(take, Value(mix.cond_sd[k]), csd);
            cmirror = dr::select(take, mirror[k], cmirror);
            crun = dr::select(take, run, crun);
            cw = dr::select(take, w[k], cw);
            done |= take && target < run + w[k];
            run += w[k];
        }
        Value cu = dr::clip((target - crun) / dr::maximum(cw, dr::Smallest<float>), 0.f, 1.f);
        Value z = phi_inv<true>(dr::fmadd(cu, cb - ca, ca)); // (P(x) / mass: x's exact density)
        // (clamped to the interval in the mirrored coordinate)
        Value x = dr::clip(cmean + csd * dr::select(cmirror, -z, z), a, b);
        // P(x, λo) = S Σ_k π_k N(λo | μo, σoo) N(x | mean_k, sd_k²), differentiable; x is
        // drawn with density exactly P/mass (detached).
        Value value = 0.f;
        for (size_t k = 0; k < n; ++k) {
            Value inv_sd = dr::rcp(mix.cond_sd[k]), e = (x - mean[k]) * inv_sd;
            value += marginal[k] * (dr::exp(-.5f * e * e) * (dr::InvSqrtTwoPi<float> * inv_sd));
        }
        dr::mask_t<Value> good = ok && total > 0.f;
        return { dr::select(good, file.scale * total, 0.f), x, dr::select(good, file.scale * value, 0.f) };
    }

    const char *m_plugin;
    std::vector<std::string> m_keys, m_filenames; ///< "filename" or "filename0".., resolved paths
    std::vector<rust::Box<fluo::MeasuredModel>> m_models;
    ref<Texture> m_index; ///< material-index texture (null: one file)
    fluo_detail::UpdateRecord<Float> m_record; ///< the traversed values, as last accepted
    bool m_gmm = false;
    Grids m_gd;          ///< the diagonals' wavelengths
    FloatStorage m_diag; ///< ρ at them
    // fluo_matrix: the λi and λo grids, P and the rows' running integrals, P's offset per file
    Grids m_gi, m_go;
    FloatStorage m_p, m_rcdf, m_cells;
    UInt32Storage m_p_off;
    /// per file: where P can be non-zero, [λi_min, λi_max, λo_min, λo_max], and fluo_gmm's
    /// scale (device arrays; the first file's on the host, constants of a one-file kernel)
    FloatStorage m_d_rect, m_d_scale;
    std::array<float, 4> m_rect{};
    float m_lambda_i_min = 0.f; ///< the smallest of the files' first λi (their rect[0])
    std::vector<float> m_scale;
    // fluo_gmm: [file][component], padded to the largest mixture
    size_t m_n_comps = 0;
    std::optional<Mixture> m_fixed_mixture; ///< mixture_at's (one file)
    std::vector<size_t> m_file_comps; ///< each file's own number of components
    mutable uint32_t m_mix_d = 0;     ///< several files, RGB: the derivative tables of this render
    mutable std::vector<Float> m_delta; ///< fluo_matrix in RGB with gradients on P: δA per entry (jit_reduced_derivatives)
    /// Several matrices: δA per file and entry ([file][kk]), the entries it holds, kk
    mutable FloatStorage m_delta_table;
    mutable std::vector<uint32_t> m_delta_entries;
    mutable size_t m_delta_kk = 0;
    std::vector<size_t> m_file_off, m_file_nodes; ///< each file's P within m_p (fluo_matrix)
    std::vector<Comp> m_comps;
    FloatStorage m_d_comp[4];              ///< the Comp fields per (file, component), for several files
    FloatStorage m_weights, m_means_i, m_means_o; ///< π_k, μi_k, μo_k (differentiable; π renormalised)
    FloatStorage m_rgb_albedo, m_rgb_elastic; ///< per file (RGB variants)
    /// several files: their reduced operators for the basis last asked for (reduced_table)
    mutable std::string m_table_key;
    mutable std::pair<std::vector<double>, bool> m_table;

    MI_TRAVERSE_CB(Base, m_gd.nodes, m_gd.d_ends, m_gd.d_size, m_diag, m_gi.nodes, m_gi.d_ends, m_gi.d_size,
                   m_go.nodes, m_go.d_ends, m_go.d_size, m_p, m_rcdf, m_cells, m_p_off, m_d_rect, m_d_scale, m_d_comp[0],
                   m_d_comp[1], m_d_comp[2], m_d_comp[3], m_weights, m_means_i, m_means_o, m_rgb_albedo,
                   m_rgb_elastic)
};

template <typename Float, typename Spectrum> class FluoMatrix final : public FluoMeasured<Float, Spectrum> {
public:
    FluoMatrix(const Properties &props)
        : FluoMeasured<Float, Spectrum>(props, "fluo_matrix", &fluo::matrix_new) {}
    MI_DECLARE_CLASS(FluoMatrix)
};

template <typename Float, typename Spectrum> class FluoGmm final : public FluoMeasured<Float, Spectrum> {
public:
    FluoGmm(const Properties &props) : FluoMeasured<Float, Spectrum>(props, "fluo_gmm", &fluo::gmm_new) {}
    MI_DECLARE_CLASS(FluoGmm)
};

static const bool fluo_measured_jit_registered =
    (fluo_detail::register_plugin<FluoMatrix>("fluo_matrix", ObjectType::BSDF),
     fluo_detail::register_plugin<FluoGmm>("fluo_gmm", ObjectType::BSDF), true);

NAMESPACE_END(mitsuba)
