#include <mitsuba/core/plugin.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/fresnel.h>
#include <mitsuba/render/ior.h>
#include <mitsuba/core/object.h>
#include <mitsuba/render/microfacet.h>
#include <mitsuba/render/texture.h>

#include <algorithm>
#include <initializer_list>
#include <optional>
#include <vector>

#include "fluo_bispectral.h"
#include "fluo_common.h"
#include "fluo_param_texture.h"
#include "fluo_qd_setup.h"

NAMESPACE_BEGIN(mitsuba)

/**!

.. _bsdf-fluo_qd:

Quantum-dot coated rough surface (:monosp:`fluo_qd`)
----------------------------------------------------

.. pluginparameters::

 * - radius
   - |float| or |texture|
   - Quantum-dot radius R in nm, in [1, 5]. Sets the absorption threshold λQD (Brus
     equation) and with it the emission colour. (Default: 2.2)
 * - width
   - |float|
   - Width δλ of the Gaussian absorption peak and of the emission band, nm, in
     [0.01, 100]. (Default: 15)
 * - quantum_yield
   - |float| or |texture|
   - Quantum yield Q in [0, 1]. (Default: 0.8)
 * - density
   - |float| or |texture|
   - Coating density ρ in [0, 1]. ρ = 0 is exactly ``roughconductor`` (or a rough
     dielectric reflection with ``int_ior``). (Default: 0.5)
 * - material
   - |string|
   - Conductor substrate by name, as ``roughconductor`` (Mitsuba's ``data/ior`` files).
     Exclusive with ``eta``/``k`` and ``int_ior``.
 * - eta, k
   - |spectrum| or |texture|
   - Conductor substrate's complex index relative to the environment. (Default:
     ``roughconductor``'s 0 and 1 when neither ``material`` nor ``int_ior`` is given)
 * - int_ior
   - |float| or |string|
   - Dielectric substrate (reflection only; transmitted light is absorbed).
 * - ext_ior
   - |float|
   - Index n_env of the environment and of the medium around the dots, in [1, 3].
     With ``int_ior`` the substrate's relative index is int_ior/ext_ior. (Default: 1.000277)
 * - distribution
   - |string|
   - ``beckmann`` or ``ggx`` (Default: ``beckmann``, as ``roughconductor``). Directions
     are sampled from the distribution of visible normals.
 * - alpha
   - |float| or |texture|
   - Roughness α in [0, 4]; 0 is clamped to 1e-4. (Default: 0.1)
 * - qd_eta, qd_k
   - |spectrum|
   - Complex index n + ik of the dot material (both or neither). (Default: cubic
     CdSe, the model dielectric function of Ninomiya & Adachi 1995)
 * - lambda_min, lambda_max
   - |float|
   - Range over which the emission is normalised and excitation is tabulated, nm.
     (Default: 300, 830)
 * - table_cos_nodes
   - |int|
   - Rows of the excitation tables A_tot(θ, λ), uniform in cos θ, in [2, 1025]: an
     accuracy/memory knob (memory and bake time grow linearly). (Default: 33)
 * - table_step
   - |float|
   - Base λ step of the excitation tables in nm, in [0.05, 50]; the grid is refined to
     δλ/8 near λQD regardless. An accuracy/memory knob. (Default: 1)
 * - gap_energy, elementary_charge, planck, light_speed, boltzmann, electron_mass,
     hole_mass, vacuum_permittivity, relative_permittivity, temperature
   - |float|
   - Constants of the Brus equation and Stokes shift in SI units. (Default: the
     CdSe values of the paper's Table 1: 2.8e-19 J, 1.6e-19 C, 6.63e-34 J s,
     3e8 m/s, 1.38e-23 J/K, 1.18e-31 kg, 4.09e-31 kg, 8.85e-12 F/m, 5.8, 293 K)

The fluorescent specular microfacet model of Benamira & Pattanaik, "A Microfacet Model
for Specular Fluorescent Surfaces and Fluorescent Volume Rendering using Quantum Dots"
(EGSR 2023), sec. 3 and 4.2: a monolayer of quantum dots of density ρ on a rough
substrate, treated as a thin film. Its bispectral Fresnel factor replaces the
substrate's Fresnel term in the microfacet BRDF (eq. 28):

.. math::

    f(ω_i, ω_o, λ_i, λ_o) = \frac{D(h)\,G(ω_i, ω_o)\,[δ(λ_i − λ_o) R_{tot}(θ, λ_i)
        + Q\,A_{tot}(θ, λ_i)\,L(λ_o)/I\;[λ_o > λ_i]]}{4 \cos θ_i \cos θ_o}

with θ the angle to the microfacet normal, R_tot and A_tot the reflectance and
absorption of the film over the substrate (multiple scattering, eqs. 23–24), and L a
logistic emission band centred on λQD + Sλ (Brus equation and Stokes shift). The
physics and our reading of each equation are in the Rust core, ``core/src/models/qd/``.

What this plugin computes in each variant:

- ``scalar_spectral``: the BSDF interface serves the elastic part, exactly
  ``roughconductor`` with its Fresnel factor R replaced by
  R_tot = R_spe + T²(1−A)²R/(1 − R R_spe) (coating coefficients from Rust). The
  reradiation is served through fluo's bispectral interface to ``fluo_path``; under
  Mitsuba's ``path`` the absorbed light is simply lost.
- ``scalar_rgb``: the elastic part per hit and per RGB channel, from the substrate's
  own (coloured) eta/k and the coating coefficients at 611, 549 and 464 nm for the
  red, green and blue channels: a gold substrate stays gold, and with a negligible
  coating the BSDF is ``roughconductor``'s in both variants. Under ``fluo_path`` the
  reradiation is added through reduced transport; its absorption tables are built
  from the substrate's spectral eta/k (a named ``material``'s data files) or, for
  RGB-valued eta/k, from the piecewise-linear spectrum through the three channel
  values at those wavelengths.
- Spatially varying (textured) ``eta``/``k`` are evaluated per hit in the elastic
  part, in every variant. The reradiation's absorption tables are baked for one
  substrate, so a textured substrate under a fluorescent coating (``density`` and
  ``quantum_yield`` > 0) is refused with an error rather than rendered with the
  substrate of one texel.

**Textured parameters.** ``radius``, ``density``, ``quantum_yield`` and ``alpha`` each take a float
texture (a one-channel ``bitmap``, a ``checkerboard``, ...), read per hit with the
texture's own ``eval_1`` (its ``to_uv`` and filter). A coating model bakes tables (2–5 ms,
~0.44 MB each), so models are baked at load on (radius, density) levels and a hit uses
the models of its bracketing levels: radii at the texture's own values (at most 16
distinct radii; more is an error: quantize the texture); densities at the texture's own
values when it has at most 9, else on 9 nodes evenly over their range. Each model is
baked with Q = 1 and scaled by the hit's Q (the reradiation is linear in Q: exact). A
hit between two levels (a filtered lookup, or a density between grid nodes) mixes the
neighbouring models with bilinear weights: ``fluo_path`` picks one of them per vertex
with that probability in ``scalar_spectral`` (an unbiased estimate of the mixture) and
sums their reduced matrices in ``scalar_rgb``; the elastic part is the same mixture.
Measured interpolation error of the density grid against the exact model at the cell
centres (reradiated XYZ at normal incidence under equal-energy light, relative to Y;
``core/src/models/qd`` test ``texture_grid_interpolation_error``): 0.73 % with 9 nodes
(0.18 % with 33). Radii get no grid because mixing two radii moves weight between two
emission peaks instead of moving the peak: 50 % / 13 % / 5.8 % off at the cell centres
of 9 / 33 / 65 nodes over R ∈ [1.5, 4] nm; at the texture's own values the model is
exact per texel, and a filtered boundary between two radii mixes the two inks. What is
validated at load, with the floats' ranges: every texel of a bitmap (NaN and
out-of-range values named with their texel, e.g. ``"radius" = 7 at texel (x = 0, y =
1)``) and the constituent values of a texture made of others (a checkerboard's
``color0``/``color1``); a ``density`` or ``quantum_yield`` texture whose values cannot be
read is checked through its mean and maximum (densities then on the grid over [0, max]),
such a ``radius`` or ``alpha`` texture is refused. A parameter given as a float, or as a
texture that does not vary, takes the uniform material's code path unchanged.

A textured ``alpha``: the elastic lobe (``eval``, ``sample``, ``pdf``) uses the hit's own
roughness, max(α, 1e-4), exactly as ``roughconductor`` with a textured alpha. The
reradiation's microfacet lobe is baked into each coating model, so models are baked
per roughness too, at the texture's own values (at most 4 distinct roughnesses; more
is an error: quantize the texture), and the grid becomes radius × density × α. A hit's
reradiation uses the models of the roughness level *nearest* to its α (no mixing
across roughnesses; radius and density keep their bilinear weights, so at most four
models per hit): exact at every texel, and a filtered lookup between two texels of
different roughness snaps the reradiation to the nearer one while the elastic lobe
takes the filtered α.

**Vectorised variants** (``llvm_ad_rgb``, ``llvm_ad_spectral``, and the cuda ones from the
same code; ``fluo_qd_jit.cpp``). The same material, evaluated per lane with Dr.Jit types:
Rust validates the parameters, builds the coating model and bakes, at load and after every
``mi.traverse`` update, A_tot(θ, λ) with its running integral along λ and the coating's
R_spe and (T_spe(1 − A_tf))² on the model's λ grid at 129 cosines; the shim interpolates
them bilinearly (within 7e-4 of A_tot's peak and 1.3e-4 of R_spe, the Rust test
``jit_tables_interpolate_the_model``), evaluates the substrate's Fresnel factor, the
microfacet lobe and the logistic emission in closed form, samples λi | λo from the A_tot
row nearest cos θi (exact inverse CDF) and forms the reradiation towards each direction
from the half vector, as the scalar variants do. In ``llvm_ad_rgb`` ``fluo_path`` uses
the scalar variant's reduced reradiation matrices at the microfacet cosines, written by
Rust as at most three terms s_t(cos θ)·B_t (a truncated SVD, within 1e-5 of the largest
entry for every coating tested; a warning names the error where it is not), so a lane
interpolates three weights instead of two K×K matrices. Images equal the scalar
variants' within noise (``test_llvm.py``). Cost against ``roughconductor`` under llvm
``path``: the ``llvm_qd`` rows of ``benches/bench_costs.py`` (README).
``quantum_yield`` is differentiable (the reradiation is linear in it), and in
``llvm_ad_spectral`` so are ``radius`` and ``density`` of a uniform material: when a render
asks for their gradient, Rust bakes the tables again at each ± 1e-3 (one-sided at the ends
of their ranges) on the model's own λ grid, and a lane's table value and emission
parameters carry value + (θ − detach(θ))·∂/∂θ from those differences (the same value; the
sampling stays detached). ``test_llvm.py`` holds AD against central differences of the
image. In ``llvm_ad_rgb`` they are baked into the reduced matrices and ``mi.traverse`` lists
them as not differentiable, as ``alpha`` and ``width``, which can be updated (the tables
are baked again) but carry no gradient; at ``density`` = 0 the material is
``roughconductor`` and has no density derivative. Textured ``radius``, ``density``, ``quantum_yield``
and ``alpha`` bake the same models on the same levels as the scalar variants (validated
alike), each with its own tables and λ grid (with its bucket index) on the device (about
1.4 MB per model). Per lane a hit reads its (radius, density) models at the roughness level
nearest its alpha, with bilinear weights, and its Q: the elastic lobe uses the hit's own
alpha and mixes its models' R_tot, as the scalar variants; the reradiation takes one model
per vertex picked with its weight as probability (an unbiased estimate of the mixture):
``llvm_ad_spectral`` with the first wavelength's choice number (rescaled within the model's
share), as ``scalar_spectral`` does with a number of its own, and ``llvm_ad_rgb`` with a
number drawn for it (``scalar_rgb`` sums the models' reduced matrices instead: the same
mean; 3·K² gathers of the picked model's terms per vertex instead of up to four times as
many). A textured parameter is not differentiable (``mi.traverse`` lists its texture).

Invalid parameters raise an error naming the parameter, its value and the valid range.
Directions are always sampled from the visible normals.

.. tabs::
    .. code-tab:: xml
        :name: fluo-qd

        <bsdf type="fluo_qd">
            <string name="material" value="Al"/>
            <string name="distribution" value="ggx"/>
            <float name="alpha" value="0.15"/>
            <float name="radius" value="3.3"/>
            <float name="density" value="0.8"/>
        </bsdf>

    .. code-tab:: python

        'type': 'fluo_qd',
        'int_ior': 1.5,
        'radius': 1.5,
        'quantum_yield': 0.9
*/
template <typename Float, typename Spectrum>
class FluoQd final : public BSDF<Float, Spectrum>, public BispectralBSDF<Float, Spectrum> {
public:
    MI_IMPORT_BASE(BSDF, m_flags, m_components)
    MI_IMPORT_TYPES(Texture, MicrofacetDistribution)

    static constexpr const char *Plugin = "fluo_qd";
    using Samples = fluo_detail::QdSamples;
    static constexpr const float *RgbWavelengths = fluo_detail::QdSetup<Float, Spectrum>::RgbWavelengths;
    using Tex = fluo_detail::QdTextures<Float, Spectrum>;

    FluoQd(const Properties &props) : Base(props) {
        using namespace fluo_detail;
        fluo::QdConfig &c = m_config; // starts as fluo::qd_default_config(): the defaults live in Rust
        // radius, density, quantum_yield, alpha: a float (the uniform fast path) or a float
        // texture; a texture that does not vary is read once as its float.
        m_tex.read(props, c);
        m_setup.parse(props, m_config, [&](const char *name) { return m_tex.textured(name); });
        m_type = m_config.ggx ? MicrofacetType::GGX : MicrofacetType::Beckmann;

        m_flags = BSDFFlags::GlossyReflection | BSDFFlags::FrontSide;
        m_components.push_back(m_flags);
        rebuild();
    }

    void traverse(TraversalCallback *cb) override {
        ScalarFloat *values[Tex::NParams] = { &m_radius, &m_density, &m_quantum_yield, &m_alpha };
        for (size_t i = 0; i < Tex::NParams; ++i) {
            if (m_tex.tex[i])
                cb->put(Tex::Names[i], m_tex.tex[i], ParamFlags::NonDifferentiable);
            else
                cb->put(Tex::Names[i], *values[i], ParamFlags::NonDifferentiable);
        }
        cb->put("width", m_width, ParamFlags::NonDifferentiable);
        cb->put("eta", m_setup.eta, ParamFlags::NonDifferentiable);
        cb->put("k", m_setup.k, ParamFlags::NonDifferentiable);
    }

    void parameters_changed(const std::vector<std::string> &keys) override {
        auto changed = [&](const char *name) { return keys.empty() || string::contains(keys, name); };
        fluo_detail::transactional_update(m_config, [&] {
            // textured parameters: rebuild() re-reads their textures
            if (changed("radius") && !m_tex.tex[Tex::Radius])       m_config.radius = m_radius;
            if (changed("width"))                                    m_config.width = m_width;
            if (changed("quantum_yield") && !m_tex.tex[Tex::Yield]) m_config.quantum_yield = m_quantum_yield;
            if (changed("density") && !m_tex.tex[Tex::Density])     m_config.density = m_density;
            if (changed("alpha") && !m_tex.tex[Tex::Alpha])         m_config.alpha = m_alpha;
        }, [&] { rebuild(); });
    }

    std::pair<BSDFSample3f, Spectrum> sample(const BSDFContext &ctx, const SurfaceInteraction3f &si,
                                             Float /* sample1 */, const Point2f &sample2,
                                             Mask active) const override {
        this->warn_if_unmanaged(Plugin);
        BSDFSample3f bs = dr::zeros<BSDFSample3f>();
        Float cos_theta_i = Frame3f::cos_theta(si.wi);
        active &= cos_theta_i > 0.f;
        if (!ctx.is_enabled(BSDFFlags::GlossyReflection) || !active)
            return { bs, 0.f };

        Float alpha = alpha_at(si, active);
        MicrofacetDistribution distr(m_type, alpha, alpha, true);
        Normal3f m;
        std::tie(m, bs.pdf) = distr.sample(si.wi, sample2);
        bs.wo = reflect(si.wi, m);
        bs.eta = 1.f;
        bs.sampled_component = 0;
        bs.sampled_type = +BSDFFlags::GlossyReflection;
        active &= (bs.pdf != 0.f) && Frame3f::cos_theta(bs.wo) > 0.f;
        if (!active)
            return { bs, 0.f };

        UnpolarizedSpectrum weight = distr.smith_g1(bs.wo, m);
        bs.pdf /= 4.f * dr::dot(bs.wo, m);
        UnpolarizedSpectrum F = fresnel_value(si, dr::dot(si.wi, m), active);
        return { bs, depolarizer<Spectrum>(F * weight) };
    }

    Spectrum eval(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
                  Mask active) const override {
        Float cos_theta_i = Frame3f::cos_theta(si.wi), cos_theta_o = Frame3f::cos_theta(wo);
        active &= cos_theta_i > 0.f && cos_theta_o > 0.f;
        if (!ctx.is_enabled(BSDFFlags::GlossyReflection) || !active)
            return 0.f;

        Vector3f H = dr::normalize(wo + si.wi);
        Float alpha = alpha_at(si, active);
        MicrofacetDistribution distr(m_type, alpha, alpha, true);
        Float D = distr.eval(H);
        if (D == 0.f)
            return 0.f;
        Float G = distr.G(si.wi, wo, H);
        UnpolarizedSpectrum result = D * G / (4.f * cos_theta_i);
        return depolarizer<Spectrum>(fresnel_value(si, dr::dot(si.wi, H), active) * result);
    }

    Float pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
              Mask active) const override {
        Float cos_theta_i = Frame3f::cos_theta(si.wi), cos_theta_o = Frame3f::cos_theta(wo);
        Vector3f m = dr::normalize(wo + si.wi);
        active &= cos_theta_i > 0.f && cos_theta_o > 0.f && dr::dot(si.wi, m) > 0.f && dr::dot(wo, m) > 0.f;
        if (!ctx.is_enabled(BSDFFlags::GlossyReflection) || !active)
            return 0.f;
        Float alpha = alpha_at(si, active);
        MicrofacetDistribution distr(m_type, alpha, alpha, true);
        return distr.eval(m) * distr.smith_g1(si.wi, m) / (4.f * cos_theta_i);
    }

    std::pair<Spectrum, Float> eval_pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si,
                                        const Vector3f &wo, Mask active) const override {
        Float cos_theta_i = Frame3f::cos_theta(si.wi), cos_theta_o = Frame3f::cos_theta(wo);
        Vector3f H = dr::normalize(wo + si.wi);
        active &= cos_theta_i > 0.f && cos_theta_o > 0.f && dr::dot(si.wi, H) > 0.f && dr::dot(wo, H) > 0.f;
        if (!ctx.is_enabled(BSDFFlags::GlossyReflection) || !active)
            return { 0.f, 0.f };
        Float alpha = alpha_at(si, active);
        MicrofacetDistribution distr(m_type, alpha, alpha, true);
        Float D = distr.eval(H);
        if (D == 0.f)
            return { 0.f, 0.f };
        Float smith_g1_wi = distr.smith_g1(si.wi, H);
        Float G = smith_g1_wi * distr.smith_g1(wo, H);
        UnpolarizedSpectrum value = D * G / (4.f * cos_theta_i);
        UnpolarizedSpectrum F = fresnel_value(si, dr::dot(si.wi, H), active);
        return { depolarizer<Spectrum>(F * value), D * smith_g1_wi / (4.f * cos_theta_i) };
    }

    /// The coating's model, in both variants: fluo_path shifts wavelengths with it in
    /// scalar_spectral and reduces it per incidence angle in scalar_rgb.
    const fluo::Fluorescence *fluorescence() const override {
        if (!m_tex.models.empty()) // textured: a representative (the largest radius and density)
            return m_tex.fluoresces ? &fluo::qd_fluorescence(*m_tex.models.back()) : nullptr;
        return fluo::qd_is_fluorescent(**m_model) ? &fluo::qd_fluorescence(**m_model) : nullptr;
    }

    const fluo::Fluorescence *fluorescence_at(const SurfaceInteraction3f &si) const override {
        if (m_tex.models.empty())
            return fluorescence();
        typename BispectralBSDF<Float, Spectrum>::Mixture mix;
        size_t n = fluorescence_local(si, mix);
        for (size_t i = 0; i < n; ++i)
            if (mix[i].model && mix[i].weight > 0.0)
                return mix[i].model;
        return nullptr;
    }

    bool fluorescence_varies() const override { return !m_tex.models.empty(); }

    /// Textured: the models of the hit's surrounding (radius, density) nodes, at the alpha
    /// level nearest the hit's, with their bilinear weights as mixture probabilities, each
    /// scaled by the hit's Q.
    size_t fluorescence_local(const SurfaceInteraction3f &si,
                              typename BispectralBSDF<Float, Spectrum>::Mixture &out) const override {
        if (m_tex.models.empty())
            return BispectralBSDF<Float, Spectrum>::fluorescence_local(si, out);
        Corners c = corners(si, true);
        for (size_t i = 0; i < c.n; ++i) {
            const fluo::QdModel &m = *m_tex.models[c.model[i]];
            out[i] = { fluo::qd_is_fluorescent(m) ? &fluo::qd_fluorescence(m) : nullptr, c.model[i], c.q,
                       c.weight[i] };
        }
        return c.n;
    }

    size_t fluorescence_models() const override { return m_tex.models.size(); }

    const fluo::Fluorescence *fluorescence_model(size_t i) const override {
        return i < m_tex.models.size() ? &fluo::qd_fluorescence(*m_tex.models[i]) : nullptr;
    }

    /// The elastic lobe alone: eval() already serves only the elastic part.
    UnpolarizedSpectrum eval_elastic(const SurfaceInteraction3f &si, const Vector3f &wo) const override {
        return unpolarized_spectrum(eval(BSDFContext(), si, wo, true));
    }

    /// Smooth-surface value R_tot(θi, λ): positive wherever the elastic lobe is.
    UnpolarizedSpectrum elastic_albedo(const SurfaceInteraction3f &si) const override {
        return fresnel_value(si, dr::maximum(Frame3f::cos_theta(si.wi), 0.f), true);
    }

    std::string to_string() const override {
        std::ostringstream oss;
        oss << "FluoQd[" << std::endl
            << "  model = " << std::string(fluo::qd_to_string(**m_model)) << "," << std::endl;
        oss << m_tex.to_string()
            << "  eta = " << string::indent(m_setup.eta) << "," << std::endl
            << "  k = " << string::indent(m_setup.k) << std::endl
            << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(FluoQd)

private:
    /// Validate the configuration in Rust and bake the model (tables included).
    void rebuild() {
        Samples eta, k, qd_eta, qd_k; // qd_eta, qd_k empty: built-in CdSe
        m_setup.sample_all(m_config, eta, k, qd_eta, qd_k);
        m_tex.bake(m_config, eta, k, qd_eta, qd_k);
        rust::Box<fluo::QdModel> model = fluo_detail::rust_call(Plugin, [&] {
            return fluo::qd_new(m_config, eta.view(), k.view(), qd_eta.view(), qd_k.view());
        });
        if (fluo::qd_is_fluorescent(*model) &&
            !m_setup.uniform_substrate())
            Throw("%s: a spatially varying substrate (textured \"eta\"/\"k\") cannot be combined "
                  "with a fluorescent coating: the coating's absorption tables are baked for one "
                  "substrate (the elastic part alone is evaluated per hit); give constant "
                  "\"eta\"/\"k\", or \"density\" = 0 or \"quantum_yield\" = 0",
                  Plugin);
        m_model = std::move(model);
        m_radius = (ScalarFloat) m_config.radius;
        m_width = (ScalarFloat) m_config.width;
        m_quantum_yield = (ScalarFloat) m_config.quantum_yield;
        m_density = (ScalarFloat) m_config.density;
        m_alpha = (ScalarFloat) m_config.alpha;
        // Mitsuba's own clamp of a zero roughness.
        m_alpha_f = dr::maximum((ScalarFloat) m_config.alpha, (ScalarFloat) 1e-4f);
        // ρ = 0: no coating, the elastic part is exactly roughconductor's.
        m_coated = m_config.density > 0.0 || (!m_tex.models.empty() && m_tex.densities.back() > 0.f);
        m_uniform_substrate = m_setup.uniform_substrate();
        m_build = fluo_detail::WavelengthMemo::next_build();
    }

    /// A textured material at a hit: up to four (radius, density) models, at the alpha
    /// level nearest the hit's, with their bilinear weights, and the hit's Q.
    struct Corners {
        size_t n = 0;
        size_t model[4]{};
        double weight[4]{};
        double q = 1.0;
    };

    /// Evaluate the parameter textures at si (Mitsuba's own eval_1: to_uv, filtering).
    Corners corners(const SurfaceInteraction3f &si, Mask active) const {
        auto value = [&](size_t i) {
            return m_tex.tex[i] ? (float) m_tex.tex[i]->eval_1(si, active)
                                : (float) Tex::field(m_config, i);
        };
        auto [ri, rt] = Tex::bracket(m_tex.radii, value(Tex::Radius));
        auto [di, dt] = Tex::bracket(m_tex.densities, value(Tex::Density));
        size_t ai = fluo_detail::nearest_level(m_tex.alphas, value(Tex::Alpha));
        float q = value(Tex::Yield);
        Corners c;
        c.q = std::isfinite(q) ? std::clamp((double) q, 0.0, 1.0) : 0.0;
        for (size_t a = 0; a < 2; ++a)
            for (size_t b = 0; b < 2; ++b) {
                double w = (a ? rt : 1.0 - rt) * (b ? dt : 1.0 - dt);
                if (!(w > 0.0))
                    continue;
                c.model[c.n] = m_tex.index(ri + a, di + b, ai);
                c.weight[c.n++] = w;
            }
        return c;
    }

    /// The elastic lobe's roughness at si: the hit's own with a textured alpha (clamped
    /// as Mitsuba's roughconductor clamps it), else the uniform m_alpha_f.
    Float alpha_at(const SurfaceInteraction3f &si, Mask active) const {
        if (!m_tex.tex[Tex::Alpha])
            return m_alpha_f;
        return dr::maximum(m_tex.tex[Tex::Alpha]->eval_1(si, active), 1e-4f);
    }

    /// The substrate's Fresnel factor, times the coating's effect when coated (eq. 23).
    UnpolarizedSpectrum fresnel_value(const SurfaceInteraction3f &si, Float cos_m, Mask active) const {
        dr::Complex<UnpolarizedSpectrum> eta_c;
        if constexpr (is_spectral_v<Spectrum>) {
            if (m_uniform_substrate) {
                // η(λ), k(λ) of a substrate uniform over the surface: per thread, asked
                // once for the wavelengths a vertex evaluates up to three times.
                std::array<float, 4> lambda = fluo_detail::wavelengths_of(si.wavelengths);
                const std::array<float, 4> &eta = fluo_detail::WavelengthMemo::get(
                    m_build, lambda, [&](std::array<float, 4> &v) { store(m_setup.eta->eval(si, active), v); });
                const std::array<float, 4> &k = fluo_detail::WavelengthMemo::get(
                    m_build, lambda, [&](std::array<float, 4> &v) { store(m_setup.k->eval(si, active), v); });
                eta_c = dr::Complex<UnpolarizedSpectrum>(UnpolarizedSpectrum(eta[0], eta[1], eta[2], eta[3]),
                                                         UnpolarizedSpectrum(k[0], k[1], k[2], k[3]));
            } else {
                eta_c = dr::Complex<UnpolarizedSpectrum>(m_setup.eta->eval(si, active), m_setup.k->eval(si, active));
            }
        } else {
            eta_c = dr::Complex<UnpolarizedSpectrum>(m_setup.eta->eval(si, active), m_setup.k->eval(si, active));
        }
        UnpolarizedSpectrum F = fresnel_conductor(UnpolarizedSpectrum(cos_m), eta_c);
        if (!m_coated)
            return F;
        std::array<float, 4> lambda{}, r_spe{}, pass{};
        if constexpr (is_spectral_v<Spectrum>)
            lambda = fluo_detail::wavelengths_of(si.wavelengths);
        else
            lambda = { RgbWavelengths[0], RgbWavelengths[1], RgbWavelengths[2], RgbWavelengths[2] };
        auto coated = [&](const fluo::QdModel &model) {
            fluo::qd_elastic_coefficients(model, (float) cos_m, fluo_detail::slice(lambda),
                                          fluo_detail::slice_mut(r_spe), fluo_detail::slice_mut(pass));
            UnpolarizedSpectrum out = F;
            for (size_t j = 0; j < dr::size_v<UnpolarizedSpectrum>; ++j) {
                float den = dr::maximum(1.f - F[j] * r_spe[j], 1e-12f);
                out[j] = r_spe[j] + pass[j] * F[j] / den;
            }
            return out;
        };
        if (m_tex.models.empty())
            return coated(**m_model);
        // textured: the elastic parts of the hit's models, mixed with their weights
        Corners c = corners(si, active);
        UnpolarizedSpectrum mixed(0.f);
        for (size_t i = 0; i < c.n; ++i)
            mixed += (float) c.weight[i] * coated(*m_tex.models[c.model[i]]);
        return mixed;
    }

    fluo::QdConfig m_config = fluo::qd_default_config(); ///< the defaults live in Rust (QdParams)
    std::optional<rust::Box<fluo::QdModel>> m_model; ///< set by rebuild() in the constructor
    MicrofacetType m_type = MicrofacetType::Beckmann;
    fluo_detail::QdSetup<Float, Spectrum> m_setup; ///< substrate, dot index
    ScalarFloat m_radius = 0.f, m_width = 0.f, m_quantum_yield = 0.f, m_density = 0.f, m_alpha = 0.f;
    ScalarFloat m_alpha_f = 0.1f;
    bool m_coated = false;
    bool m_uniform_substrate = true; ///< η and k do not vary over the surface
    uint64_t m_build = 0;            ///< this build's key in the per-thread η, k memo

    static void store(const UnpolarizedSpectrum &s, std::array<float, 4> &out) {
        for (size_t j = 0; j < 4; ++j)
            out[j] = s[j];
    }
    /// textured radius, density, quantum_yield, alpha: their textures, levels, baked models
    Tex m_tex;
};

static const bool fluo_qd_registered =
    (fluo_detail::register_scalar_plugin<FluoQd>("fluo_qd", ObjectType::BSDF), true);

NAMESPACE_END(mitsuba)
