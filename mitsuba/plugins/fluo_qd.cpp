// fluo_qd, one class template for every variant it serves (the documentation below).
//
// Rust validates the parameters, builds the coating model and bakes, at load and in
// parameters_changed(), what the plugin interpolates per lane (fluo::qd_jit_tables): on the
// model's λ grid and JitCosNodes cosines, A_tot (the reradiation's absorption) with its running
// integral along λ, and the coating's R_spe and pass = (T_spe (1 − A_tf))²; bilinear in
// (cos θ, λ) they stay within 7e-4 of A_tot's peak and 1.3e-4 of R_spe and pass (Rust test
// jit_tables_interpolate_the_model). Per lane the plugin evaluates with Dr.Jit types:
// - the elastic lobe: Mitsuba's microfacet distribution (as roughconductor) with the Fresnel
//   factor R_tot = R_spe + pass·F/(1 − F·R_spe) over the substrate's own F (its eta/k
//   textures, spectral ones read on their own nodes: IorTable); RGB variants take R_spe
//   and pass at the channels' wavelengths.
// - the shift (spectral): λi | λo sampled ∝ the A_tot row nearest cos θi on the excitation
//   interval (its CDF inverted exactly, the cell's quadratic root), weighted by the logistic
//   emission e(λo | λi) = L(λo)/I and Q; the reradiation towards ωo is
//   D G/(4 cos θi)·Q·A_tot(ωi·h, λi)·e(λo | λi).
// - RGB: Rust's reduced reradiation matrices at the microfacet cosines, as a few terms
//   s_t(cos θ)·B_t (a truncated SVD, within 1e-5), scaled by the lobe.
#include <mitsuba/core/properties.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/fresnel.h>
#include <mitsuba/render/mueller.h>
#include <mitsuba/render/microfacet.h>
#include <mitsuba/render/texture.h>

#include <algorithm>
#include <atomic>
#include <cstring>
#include <optional>
#include <string>
#include <vector>

#include "fluo_common.h"
#include "fluo_bispectral.h"
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

What this plugin computes in each variant (``scalar_*``, ``llvm_ad_*``, ``cuda_ad_*``;
one class, ``fluo_qd.cpp``):

- Spectral variants: the BSDF interface serves the elastic part, ``roughconductor``
  with its Fresnel factor R replaced by R_tot = R_spe + T²(1−A)²R/(1 − R R_spe)
  (coating coefficients from Rust's tables, the substrate's R per lane). The
  reradiation is served through fluo's bispectral interface to ``fluo_path``; under
  Mitsuba's ``path`` the absorbed light is simply lost.
- Polarized spectral variants: the elastic lobe is the substrate's Mueller matrix for
  specular reflection off the microfacet (as ``roughconductor``), scaled to intensity
  R_tot: the coating's tables are averaged over polarization, so the coating scales the
  substrate's matrix (exact without a coating, approximate in its polarization with one);
  reradiated light leaves unpolarized.
- RGB variants: the elastic part per hit and per RGB channel, from the substrate's
  own (coloured) eta/k and the coating coefficients at 611, 549 and 464 nm for the
  red, green and blue channels: a gold substrate stays gold, and with a negligible
  coating the BSDF is ``roughconductor``'s in every variant. Under ``fluo_path`` the
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
with that probability (an unbiased estimate of the mixture; in the RGB variants its
reduced reradiation); the elastic part mixes the models' R_tot with those weights.
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

**Evaluation** (every variant). Rust validates the parameters, builds the coating model
and bakes, at load and after every ``mi.traverse`` update, A_tot(θ, λ) with its running
integral along λ and the coating's R_spe and (T_spe(1 − A_tf))² on the model's λ grid at
65 cosines; the plugin interpolates them bilinearly per lane (within 7e-4 of A_tot's
peak and 1.3e-4 of R_spe, the Rust test ``jit_tables_interpolate_the_model``; 0.97 MB of
float tables per coating, every coating's in one array of the process, so that many
coatings read theirs per lane from it; the grid is uniform between λmin, λQD ± 10 δλ,
λQD and λmax, so that a lane finds its cell by arithmetic; R_spe and pass of a node and
of the next are kept side by side, 4 floats read at once: 0.28 MB of the 0.97), evaluates
the substrate's Fresnel factor, the microfacet lobe and the logistic emission in closed
form (the substrate's ``uniform`` or ``irregular`` eta and k spectra, as ``material``'s
are, read per lane from their own nodes with one cell lookup for both: Mitsuba's values,
without a search per spectrum), samples λi | λo from the A_tot row nearest cos θi (exact inverse CDF) and forms the
reradiation towards each direction from the half vector. No variant calls Rust per
vertex. In the RGB variants ``fluo_path`` uses Rust's reduced reradiation matrices at the
microfacet cosines, written by Rust as at most three terms s_t(cos θ)·B_t (a truncated
SVD, within 1e-5 of the largest entry for every coating tested in the fixed bases, 6e-5 in
``auto``; a warning names the error above 1e-4), so a lane interpolates three weights instead of two K×K matrices. Cost
against ``roughconductor`` under llvm ``path``: the ``llvm_qd`` rows of
``benches/bench_costs.py`` (README). Textured ``radius``, ``density``, ``quantum_yield``
and ``alpha`` bake the models described above, each with its own tables and λ grid (with
its bucket index; about 1.4 MB per model). Per lane a hit reads its (radius, density)
models at the roughness level nearest its alpha, with bilinear weights, and its Q: the
elastic lobe uses the hit's own alpha and mixes its models' R_tot; the reradiation takes
one model per vertex picked with its weight as probability (an unbiased estimate of the
mixture): in the spectral variants with the first wavelength's choice number (rescaled
within the model's share), in the RGB variants with a number drawn for it (3·K² gathers
of the picked model's terms per vertex instead of up to four times as many).

**Gradients** (``llvm_ad_*``, ``cuda_ad_*``). ``quantum_yield`` is differentiable (the
reradiation is linear in it), and so are ``radius`` and ``density`` of a uniform
material: when a render asks for their gradient, Rust bakes the
tables again at each ± 1e-3 (one-sided at the ends of their ranges) on the model's own λ
grid, and a lane's table value and emission parameters carry value + (θ − detach(θ))·∂/∂θ
from those differences (the same value; the sampling stays detached). In the RGB variants,
where they are baked into the reduced matrices, the RGB tables (R_spe, pass at the
channels) carry the same tangents, and the reduced reradiation's derivative at each
cosine node (central differences of Rust's reductions at ± 1e-2, per unit Q) is added per
lane between the nodes with weight θ − detach(θ), computed at a render's start only while
they carry gradients. ``test_llvm.py`` holds AD against central differences of the image
in both variants. ``width`` can be updated (the tables are baked again) but carries no
gradient.
``alpha`` of a uniform material is differentiable in every AD variant: no table depends on
it, the microfacet lobe D·G/(4 cos θi) is evaluated per lane from it (the sampled directions
are detached and the lobe's value differentiated there, as Mitsuba's ``path`` and ``prb``
do for ``roughconductor``). At ``density`` = 0 the material is ``roughconductor`` and has
no density derivative. A textured parameter is not differentiable (``mi.traverse`` lists its
texture).

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
class FluoQd final : public BSDF<Float, Spectrum>, public fluo_detail::BispectralBSDF<Float, Spectrum> {
public:
    MI_IMPORT_BASE(BSDF, m_flags, m_components)
    MI_IMPORT_TYPES(Texture, MicrofacetDistribution)
    using WMask = dr::mask_t<UnpolarizedSpectrum>;
    using FloatStorage = DynamicBuffer<Float>;
    using UInt32Storage = DynamicBuffer<UInt32>;
    using Setup = fluo_detail::QdSetup<Float, Spectrum>;
    using Tex = fluo_detail::QdTextures<Float, Spectrum>;
    using Bispectral = fluo_detail::BispectralBSDF<Float, Spectrum>;
    using Bispectral::MaxTerms;
    using Choice = typename Bispectral::Choice;
    using Joined = typename Bispectral::Joined;
    /// A textured hit mixes at most four models: two radii by two densities.
    static constexpr size_t MaxCorners = 4;

    static constexpr const char *Plugin = "fluo_qd";
    /// Rows of the interpolated tables, uniform in cos θ (the Rust test measures the error at
    /// this many: within 7e-4 of A_tot's peak, the λ grid's share dominating on metals; 129
    /// rows cut the cos θ share from 5e-4 to 1.4e-4 on glass at twice the memory).
    static constexpr size_t JitCosNodes = 65;

    FluoQd(const Properties &props) : Base(props) {
        m_tex.read(props, m_config);
        m_setup.parse(props, m_config, [&](const char *name) { return m_tex.textured(name); });
        m_type = m_config.ggx ? MicrofacetType::GGX : MicrofacetType::Beckmann;
        m_flags = BSDFFlags::GlossyReflection | BSDFFlags::FrontSide;
        m_components.push_back(m_flags);
        rebuild();
        sync_members();
    }

    /// A textured parameter is listed as its texture (not differentiable).
    void traverse(TraversalCallback *cb) override {
        m_record.arm(this);
        Base::traverse(cb);
        // Q: differentiable; radius and density: in every variant of a uniform material (tangents(); RGB:
        // the reduced operator's derivative at the cosine nodes, jit_reduced_derivatives); alpha: in every
        // AD variant of a uniform material (the lobe D·G/(4 cos θi) is evaluated per lane from it; no table
        // depends on it)
        for (auto [i, value] : params()) {
            if (m_tex.tex[i])
                cb->put(Tex::Names[i], m_tex.tex[i], ParamFlags::NonDifferentiable);
            else
                cb->put(Tex::Names[i], *value,
                        i == Tex::Yield || !m_tex.any() ? ParamFlags::Differentiable : ParamFlags::NonDifferentiable);
        }
        cb->put("width", m_width, ParamFlags::NonDifferentiable);
        cb->put("eta", m_setup.eta, ParamFlags::NonDifferentiable);
        cb->put("k", m_setup.k, ParamFlags::NonDifferentiable);
    }

    /// Rust validates the new values and bakes the tables again (textured parameters: their
    /// textures are read again); a rejected update restores the previous ones, so the
    /// material keeps working. Q keeps its AD graph (the reradiation is linear in it).
    void parameters_changed(const std::vector<std::string> &keys) override {
        m_record.update(this, m_config, [&] {
            for (auto [i, value] : params())
                if (!m_tex.tex[i])
                    Tex::field(m_config, i) =
                        fluo_detail::updated_param(Plugin, Tex::Names[i], *value, Tex::field(m_config, i));
            m_config.width = fluo_detail::updated_param(Plugin, "width", m_width, m_config.width);
            rebuild();
            // gradients asked for (an optimiser's update): the tangents now, outside any trace
            tangents();
            if (!m_tex.any() && dr::grad_enabled(m_alpha)) // the roughness keeps its AD graph
                m_alpha_v = dr::maximum(m_alpha, 1e-4f);
        });
        Base::parameters_changed(keys);
    }

    std::pair<BSDFSample3f, Spectrum> sample(const BSDFContext &ctx, const SurfaceInteraction3f &si,
                                             Float /* sample1 */, const Point2f &sample2,
                                             Mask active) const override {
        this->warn_if_unmanaged(Plugin);
        return sample_with(ctx, si, sample2, active, hit(si, active, true));
    }

    Spectrum eval(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
                  Mask active) const override {
        return eval_pdf_with(ctx, si, wo, active, hit(si, active, true)).first;
    }

    Float pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
              Mask active) const override {
        Float cos_theta_i = Frame3f::cos_theta(si.wi), cos_theta_o = Frame3f::cos_theta(wo);
        Vector3f m = dr::normalize(wo + si.wi);
        active &= cos_theta_i > 0.f && cos_theta_o > 0.f && dr::dot(si.wi, m) > 0.f && dr::dot(wo, m) > 0.f;
        if (unlikely(!ctx.is_enabled(BSDFFlags::GlossyReflection) || dr::none_or<false>(active)))
            return 0.f;
        Float alpha = elastic_alpha(param(si, Tex::Alpha, active));
        MicrofacetDistribution distr(m_type, alpha, alpha, true);
        return dr::select(active, distr.eval(m) * distr.smith_g1(si.wi, m) / (4.f * cos_theta_i), 0.f);
    }

    std::pair<Spectrum, Float> eval_pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si,
                                        const Vector3f &wo, Mask active) const override {
        return eval_pdf_with(ctx, si, wo, active, hit(si, active, true));
    }

    /// eval_pdf and sample sharing the hit's models and table cells.
    std::tuple<Spectrum, Float, BSDFSample3f, Spectrum> eval_pdf_sample(const BSDFContext &ctx,
                                                                        const SurfaceInteraction3f &si,
                                                                        const Vector3f &wo, Float /* sample1 */,
                                                                        const Point2f &sample2,
                                                                        Mask active) const override {
        this->warn_if_unmanaged(Plugin);
        if constexpr (dr::is_jit_v<Float>)
            return eval_pdf_sample_with(ctx, si, wo, sample2, active);
        else
            return eval_pdf_sample_inlined(ctx, si, wo, sample2, active);
    }
    __attribute__((flatten)) std::tuple<Spectrum, Float, BSDFSample3f, Spectrum>
    eval_pdf_sample_inlined(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
                            const Point2f &sample2, Mask active) const {
        return eval_pdf_sample_with(ctx, si, wo, sample2, active);
    }
    std::tuple<Spectrum, Float, BSDFSample3f, Spectrum> eval_pdf_sample_with(const BSDFContext &ctx,
                                                                             const SurfaceInteraction3f &si,
                                                                             const Vector3f &wo, const Point2f &sample2,
                                                                             Mask active) const {
        Hit h = hit(si, active, true);
        auto [value, pdf] = eval_pdf_with(ctx, si, wo, active, h);
        auto [bs, weight] = sample_with(ctx, si, sample2, active, h);
        return { value, pdf, bs, weight };
    }

    // ------------------------------------------------ fluo_path's interface (fluo_bispectral.h)
    bool jit_fluorescent() const override {
        if (textured())
            return m_tex.fluoresces;
        // Q = 0 re-emits nothing, but with gradients on Q its derivative does (m_unit)
        return fluo::qd_is_fluorescent(**m_model) || (m_unit && dr::grad_enabled(m_q));
    }
    /// The coating whose tables and ranges a uniform material bakes: its own, or at Q = 0
    /// the same coating at Q = 1 (nothing in the tables depends on Q; Q weights the
    /// reradiation per lane), so that dQ at Q = 0 has a shift to flow through.
    const fluo::QdModel &baked() const { return m_unit ? **m_unit : **m_model; }
    /// The emission range (textured: the hull of the fluorescent models').
    fluo::Range jit_emission_range() const override {
        if (!textured())
            return fluo::fluo_emission_range(fluo::qd_fluorescence(baked()));
        std::vector<const fluo::Fluorescence *> f;
        for (const auto &m : m_tex.models)
            f.push_back(fluo::qd_is_fluorescent(*m) ? &fluo::qd_fluorescence(*m) : nullptr);
        return fluo_detail::emission_hull(f);
    }
    fluo::Range jit_excitation_range() const override {
        if (textured())
            return { 0.0, 1e30 };
        return fluo::fluo_excitation_range(fluo::qd_fluorescence(baked()));
    }
    bool jit_lambertian() const override { return false; }

    /// No Lambertian operator: jit_reduced_nodes (jit_reduced_nodes_table) serves the reradiation.
    bool jit_reduced_matrices(const fluo::TransportBasis &, std::array<std::vector<double>, MaxTerms> &) const override {
        return false;
    }
    /// Rust's reduced matrices at the microfacet cosines, per unit Q (w_0 = Q carries it), as
    /// at most MaxTerms terms s_t(cos θ)·B_t (a truncated SVD: within 1e-5 of the largest
    /// entry for every coating measured; a warning says so where it is not).
    size_t jit_reduced_nodes(const fluo::TransportBasis &transport, std::array<std::vector<double>, MaxTerms> &m,
                             std::vector<double> &nodes) const override {
        // fluo_path asks once per render; the reduction (17 operators) is kept per basis
        // until the model is rebuilt.
        std::string key = std::string(fluo::transport_label(transport)) + "/" + std::to_string(m_build);
        if (key != m_reduced_key) {
            size_t kk = m[0].size();
            std::vector<double> basis;
            double error = 0.0;
            m_reduced_n = reduce_nodes(baked(), m_unit ? 1.0 : m_config.quantum_yield, transport, kk, basis,
                                       m_reduced_nodes, error);
            warn_low_rank(error, "this coating");
            for (size_t t = 0; t < MaxTerms; ++t)
                m_reduced_m[t].assign(basis.begin() + (std::ptrdiff_t) (t * kk),
                                      basis.begin() + (std::ptrdiff_t) ((t + 1) * kk));
            m_reduced_key = key;
        }
        m = m_reduced_m;
        nodes = m_reduced_nodes;
        return m_reduced_n;
    }
    std::array<Float, MaxTerms> jit_reduced_weights() const override { return { m_q, Float(0.f), Float(0.f) }; }

    /// RGB with gradients on radius or density (a uniform material): ∂M_j/∂θ of the reduced
    /// reradiation at each cosine node (per unit Q, as jit_reduced_nodes), central differences
    /// of Rust's reductions at θ ± NodeStep (one-sided at a range end); fluo_path adds them
    /// per lane between the nodes with the weights θ − detach(θ).
    size_t jit_reduced_derivatives(const fluo::TransportBasis &transport,
                                   std::vector<std::vector<double>> &d) const override {
        if (textured() || !(wants(0) || wants(1)))
            return 0;
        size_t kk = fluo::transport_size(transport) * fluo::transport_size(transport);
        const fluo_detail::QdSamples &eta = m_samples[0], &k = m_samples[1], &qd_eta = m_samples[2],
                                     &qd_k = m_samples[3];
        for (size_t p = 0; p < 2; ++p) {
            if (!wants(p))
                continue;
            // the node matrices M_j = Σ_t w[j][t]·B_t at θ + δ (Q = 1), or nothing out of range
            auto at = [&](double delta) -> std::optional<std::vector<double>> {
                fluo::QdConfig c = m_config;
                c.quantum_yield = 1.0;
                (p == 0 ? c.radius : c.density) += delta;
                std::vector<double> basis, nodes;
                double error = 0.0;
                size_t n = 0;
                try {
                    rust::Box<fluo::QdModel> m = fluo::qd_new(c, eta.view(), k.view(), qd_eta.view(), qd_k.view());
                    n = reduce_nodes(*m, 1.0, transport, kk, basis, nodes, error);
                } catch (const std::exception &) {
                    return std::nullopt;
                }
                std::vector<double> full(n * kk, 0.0);
                for (size_t j = 0; j < n; ++j)
                    for (size_t t = 0; t < MaxTerms; ++t)
                        for (size_t i = 0; i < kk; ++i)
                            full[j * kk + i] += nodes[j * MaxTerms + t] * basis[t * kk + i];
                return full;
            };
            std::optional<std::vector<double>> dp = fluo_detail::central_difference(NodeStep, at);
            if (!dp)
                Throw("%s: no derivative of the reduced reradiation in \"%s\" at %f", Plugin,
                      p == 0 ? "radius" : "density", p == 0 ? m_config.radius : m_config.density);
            d.push_back(std::move(*dp));
        }
        return d.size();
    }
    /// RGB node derivatives (radius, density in that order, those carrying gradients).
    std::vector<Float> jit_reduced_derivative_weights(const SurfaceInteraction3f & /* si */,
                                                      Mask /* active */) const override {
        std::vector<Float> w;
        for (size_t p = 0; p < 2; ++p)
            if (wants(p))
                w.push_back(delta(p));
        return w;
    }
    /// The step of jit_reduced_derivatives' differences (nm for radius; density): the node
    /// matrices come through a truncated SVD held to ~1e-5 of the largest entry, which a step
    /// of 1e-3 would amplify to ~1 % of the derivative.
    static constexpr double NodeStep = 1e-2;

    /// Textured: every baked model's terms (Q = 1: the hit's Q enters the corners' weights).
    size_t jit_reduced_nodes_table(const fluo::TransportBasis &transport, std::vector<double> &m,
                                   std::vector<double> &nodes, size_t &n_nodes) const override {
        if (!textured())
            return 0;
        size_t kk = fluo::transport_size(transport) * fluo::transport_size(transport);
        std::string key = std::string(fluo::transport_label(transport)) + "/" + std::to_string(m_build) + "/table";
        if (key != m_table_key) {
            m_table_m.clear();
            m_table_nodes.clear();
            double worst = 0.0;
            for (const auto &model : m_tex.models) {
                std::vector<double> basis, s;
                if (fluo::qd_is_fluorescent(*model)) {
                    double error = 0.0;
                    m_table_n = reduce_nodes(*model, 1.0, transport, kk, basis, s, error);
                    worst = std::max(worst, error);
                } else { // density 0: nothing re-emitted
                    m_table_n = fluo::reduced_microfacet_nodes();
                    basis.assign(MaxTerms * kk, 0.0);
                    s.assign(m_table_n * MaxTerms, 0.0);
                }
                m_table_m.insert(m_table_m.end(), basis.begin(), basis.end());
                m_table_nodes.insert(m_table_nodes.end(), s.begin(), s.end());
            }
            warn_low_rank(worst, "the least well held of this material's coatings");
            m_table_key = key;
        }
        m = m_table_m;
        nodes = m_table_nodes;
        n_nodes = m_table_n;
        return m_tex.models.size();
    }
    /// One of the hit's (radius, density) models at the alpha level nearest its roughness,
    /// picked with its bilinear weight as probability by u, and the hit's Q.
    std::pair<UInt32, Float> jit_reduced_pick(const SurfaceInteraction3f &si, const Float &u,
                                              Mask active) const override {
        Hit h = hit(si, active, false);
        Pick p = pick(h, u);
        return { p.model.index, h.q };
    }

    /// The microfacet lobe D G/(4 cos θi) and cos θ = ωi·h (as the Rust model's lobe, at the
    /// roughness the hit's models were baked with).
    std::pair<Float, Float> jit_lobe(const SurfaceInteraction3f &si, const Vector3f &wo, Mask active) const override {
        Float alpha = m_alpha_v;
        if (textured())
            alpha = level_alpha(fluo_detail::lane_nearest(m_tex.alphas, param(si, Tex::Alpha, active)));
        return lobe(si, wo, alpha, active);
    }

    /// Smooth-surface R_tot(θi, λ) (spectral), or per RGB channel.
    UnpolarizedSpectrum jit_elastic_albedo(const SurfaceInteraction3f &si, Mask active) const override {
        return fresnel_value(si, dr::maximum(Frame3f::cos_theta(si.wi), 0.f), active, hit(si, active, true));
    }

    /// Textured: one of the hit's (radius, density) models, picked with its bilinear weight
    /// as probability by the first wavelength's u1 (then rescaled within the model's share:
    /// still uniform for the elastic/shift choice), scaled by the hit's Q; its index is
    /// `local` (an unbiased estimate of the mixture).
    Choice jit_choose(const SurfaceInteraction3f &si, const Wavelength &u1, const Wavelength &u2, double range_lo,
                      double range_hi, Mask active) const override {
        if constexpr (!is_spectral_v<Spectrum>) {
            (void) u1, (void) u2, (void) range_lo, (void) range_hi, (void) active;
            return this->elastic_only(si.wavelengths);
        } else {
            return choose_at(hit(si, active, false), si, u1, u2, range_lo, range_hi, active);
        }
    }

    /// Many materials: a uniform coating without gradients joins the others of its class
    /// and distribution as one model of a joined table set (as a textured material's
    /// models), with its own Q and roughness.
    bool jit_joinable() const override {
        return dr::is_jit_v<Float> && !textured() && (!is_spectral_v<Spectrum> || m_tables.size() > 0) &&
               !dr::grad_enabled(m_q) && !dr::grad_enabled(m_radius) && !dr::grad_enabled(m_density) &&
               !dr::grad_enabled(m_alpha) && !dr::grad_enabled(m_alpha_v);
    }
    /// The distribution, and what the joined elastic lobe (jit_eval_pdf_sample_joined) reads
    /// of the first member for all: whether it is coated and its substrate (eta and k: their
    /// textures' descriptions and their values as Rust got them, at every nm of the
    /// material's range; one varying over the surface joins none).
    std::string jit_join_tag() const override {
        std::ostringstream tag;
        tag << (m_type == MicrofacetType::GGX ? "ggx" : "beckmann") << (m_coated ? "/coated/" : "/bare/");
        if (!m_setup.uniform_substrate())
            return tag.str() + std::to_string(m_build);
        tag << m_setup.eta->to_string() << '/' << m_setup.k->to_string() << '/';
        for (const fluo_detail::QdSamples *q : { &m_samples[0], &m_samples[1] })
            for (const std::vector<double> *v : { &q->wavelengths, &q->values }) {
                tag << v->size() << ':';
                tag.write(reinterpret_cast<const char *>(v->data()), (std::streamsize) (v->size() * sizeof(double)));
            }
        return tag.str();
    }
    bool jit_elastic_joined() const override { return dr::is_jit_v<Float>; }
    Joined jit_join(const std::vector<const Bispectral *> &members) const override {
        // the tables are joined again only where a member was rebuilt (or the members changed)
        std::vector<std::pair<const void *, uint64_t>> key;
        for (const Bispectral *b : members) {
            const auto *m = static_cast<const FluoQd *>(b);
            if (m->m_rows != m_rows)
                return nullptr; // (one table layout per class)
            key.emplace_back(m, m->m_build);
        }
        if (!m_joined || m_joined->key != key) {
            auto j = std::make_shared<JoinedTables>();
            if constexpr (is_spectral_v<Spectrum>) {
                std::vector<float> emission;
                std::vector<uint32_t> t_off, t_len; // (the members' blocks, read where they are)
                for (const Bispectral *b : members) {
                    const auto *m = static_cast<const FluoQd *>(b);
                    t_off.push_back(m->m_tables.at());
                    t_len.push_back(m->m_len);
                    for (const Float &v : m->m_em)
                        emission.push_back(dr::slice(dr::detach(v)));
                    j->grids.add(m->m_grid.host, true);
                }
                j->grids.upload();
                j->emission = dr::load<FloatStorage>(emission.data(), emission.size());
                j->t_off = dr::load<UInt32Storage>(t_off.data(), t_off.size());
                j->t_len = dr::load<UInt32Storage>(t_len.data(), t_len.size());
            } else { // the members' channel rows, [member][rows][8] (the elastic lobe's)
                std::vector<float> rows;
                for (const Bispectral *b : members) {
                    const FloatStorage &m = static_cast<const FluoQd *>(b)->m_rgb_rows;
                    std::vector<float> v = fluo_detail::host_lanes(m, dr::width(m));
                    rows.insert(rows.end(), v.begin(), v.end());
                }
                j->rgb_rows = dr::load<FloatStorage>(rows.data(), rows.size());
            }
            j->key = std::move(key);
            m_joined = std::move(j);
        }
        // each member's Q and roughness, read at every join (a few floats)
        std::vector<float> q, alpha;
        for (const Bispectral *b : members) {
            const auto *m = static_cast<const FluoQd *>(b);
            q.push_back(dr::slice(dr::detach(m->m_q)));
            alpha.push_back(dr::slice(dr::detach(m->m_alpha_v)));
        }
        auto j = m_joined ? std::make_shared<JoinedTables>(*m_joined) : std::make_shared<JoinedTables>();
        j->q = dr::load<FloatStorage>(q.data(), q.size());
        j->alpha = dr::load<FloatStorage>(alpha.data(), alpha.size());
        return j;
    }
    Choice jit_choose_joined(const Joined &joined, const UInt32 &member, const SurfaceInteraction3f &si,
                             const Wavelength &u1, const Wavelength &u2, double range_lo, double range_hi,
                             Mask active) const override {
        if constexpr (!is_spectral_v<Spectrum>) {
            (void) joined, (void) member, (void) u1, (void) u2, (void) range_lo, (void) range_hi, (void) active;
            return this->elastic_only(si.wavelengths);
        } else {
            return choose_at(joined_hit(*static_cast<const JoinedTables *>(joined.get()), member, si, active, false),
                             si, u1, u2, range_lo, range_hi, active);
        }
    }
    typename Bispectral::EvalPdfSample jit_eval_pdf_sample_joined(const Joined &joined, const UInt32 &member,
                                                                  const BSDFContext &ctx,
                                                                  const SurfaceInteraction3f &si, const Vector3f &wo,
                                                                  const Float & /* sample1 */,
                                                                  const Point2f &sample2, Mask active) const override {
        Hit h = joined_hit(*static_cast<const JoinedTables *>(joined.get()), member, si, active, true);
        auto [value, pdf] = eval_pdf_with(ctx, si, wo, active, h);
        auto [bs, weight] = sample_with(ctx, si, sample2, active, h);
        return { value, pdf, bs, weight };
    }
    std::pair<Float, Float> jit_lobe_joined(const Joined &joined, const UInt32 &member, const SurfaceInteraction3f &si,
                                            const Vector3f &wo, Mask active) const override {
        const auto &j = *static_cast<const JoinedTables *>(joined.get());
        return lobe(si, wo, fluo_detail::fetch<Float>(j.alpha, member, active), active);
    }
    std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum>
    jit_reradiation_joined(const Joined &joined, const SurfaceInteraction3f &si, const UnpolarizedSpectrum &rerad,
                           const UInt32 &local, const Vector3f &wo_a, const Vector3f &wo_b,
                           Mask active) const override {
        const auto &j = *static_cast<const JoinedTables *>(joined.get());
        return reradiation_at(joined_model(j, local, active), fluo_detail::fetch<Float>(j.alpha, local, active), si, rerad,
                              wo_a, wo_b, active);
    }

    /// lobe(ωi, ωo)·A_tot(ωi·h, λi)·rerad towards both directions (si.wavelengths = λi), of
    /// the model jit_choose picked (`local`; textured: its roughness level's lobe).
    std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum> jit_reradiation(const SurfaceInteraction3f &si,
                                                                        const UnpolarizedSpectrum &rerad,
                                                                        const UInt32 &local, const Vector3f &wo_a,
                                                                        const Vector3f &wo_b,
                                                                        Mask active) const override {
        Float alpha = textured() ? level_alpha(local % (uint32_t) m_tex.alphas.size()) : m_alpha_v;
        return reradiation_at(model_at(local, active), alpha, si, rerad, wo_a, wo_b, active);
    }

    std::string to_string() const override {
        std::ostringstream oss;
        oss << "FluoQd[" << std::endl
            << "  model = " << std::string(fluo::qd_to_string(**m_model)) << "," << std::endl
            << m_tex.to_string()
            << "  eta = " << string::indent(m_setup.eta) << "," << std::endl
            << "  k = " << string::indent(m_setup.k) << "," << std::endl
            << "  evaluation = tables per lane, " << m_rows << " x " << grid_max() << std::endl
            << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(FluoQd)

private:
    /// λ in the table's cell k (λ_k = x0 ≤ λ ≤ λ_{k+1} = x1, clamped to the grid) at fraction f.
    /// (Value: Float, or a lane's hero wavelengths: Wavelength)
    template <typename Value> using CellOf = typename fluo_detail::LaneGrid<Float>::template CellOf<Value>;
    using Cell = CellOf<Float>;
    /// The cells of a hit's hero wavelengths, one packet (spectral; unused in RGB).
    using Cells = CellOf<Wavelength>;
    using UInt32W = dr::uint32_array_t<Wavelength>;
    using WaveMask = dr::mask_t<Wavelength>;
    using GridAt = typename fluo_detail::LaneGridSet<Float>::At;

    bool textured() const { return !m_tex.models.empty(); }
    /// The longest λ grid of the baked models.
    uint32_t grid_max() const { return textured() ? m_grids.n_max : m_grid.n; }

    /// Many materials: the tables of the members of a class (jit_join), as a textured
    /// material's models (one per member), with each member's Q and roughness.
    struct JoinedTables {
        fluo_detail::LaneGridSet<Float> grids;
        FloatStorage emission, q, alpha;
        UInt32Storage t_off, t_len; ///< each member's block in the table store and its table length
        FloatStorage rgb_rows; ///< RGB: each member's channel rows, [member][rows][8] (rgb_rows())
        std::vector<std::pair<const void *, uint64_t>> key; ///< the members and their builds
    };

    /// One baked model as a lane reads it: its tables in the table store ([rows][n] row
    /// major, table k at off + k·len) and its λ grid (textured; a uniform material's is
    /// m_grid, with its bucket index).
    struct ModelAt {
        UInt32 index, off, len, n;
        GridAt grid;
        const JoinedTables *joined = nullptr; ///< the grids and emission read (null: the material's own)
    };
    ModelAt joined_model(const JoinedTables &j, const UInt32 &m, const Mask &active) const {
        GridAt g = j.grids.at(m, active);
        return { m, fluo_detail::fetch<UInt32>(j.t_off, m, active), fluo_detail::fetch<UInt32>(j.t_len, m, active), g.n, g, &j };
    }
    /// The tables of a block, each [rows][n] per model: A_tot, its running integral along λ,
    /// the smooth surface's R_tot, R_spe and pass (Rust's QdJitTables). In the store, R_spe
    /// and pass come first, as film() reads them, then the others.
    enum Table : uint32_t { ATot, Cdf, RTot, RSpe, Pass, Tables };
    /// Where table k (ATot, Cdf or RTot) of model mo starts in the table store.
    static UInt32 start(const ModelAt &mo, Table k) { return mo.off + (4 + (uint32_t) k) * mo.len; }
    const FloatStorage &store() const { return m_tables.data(); }
    uint32_t grid_max(const ModelAt &mo) const { return mo.joined ? mo.joined->grids.n_max : grid_max(); }
    ModelAt model_at(const UInt32 &m, const Mask &active) const {
        if (!textured())
            return { UInt32(0), m_tables.offset(), m_len_v, m_grid.v_n, GridAt{} };
        GridAt g = m_grids.at(m, active);
        return { m, m_tables.offset() + fluo_detail::fetch<UInt32>(m_t_off, m, active), m_len_v, g.n, g };
    }
    static ModelAt select_model(const Mask &m, const ModelAt &a, const ModelAt &b) {
        return { dr::select(m, a.index, b.index), dr::select(m, a.off, b.off), dr::select(m, a.len, b.len),
                 dr::select(m, a.n, b.n), dr::select(m, a.grid, b.grid), a.joined };
    }

    /// The cell of λ in a model's grid (a uniform material: m_grid's arithmetic over its
    /// uniform segments; textured, joined: LaneGridSet's bucket index); λ a
    /// Float or the packet of a lane's hero wavelengths.
    template <typename Value>
    CellOf<Value> cell(const ModelAt &mo, const Value &lambda, const dr::mask_t<Value> &active) const {
        if (!textured() && !mo.joined)
            return m_grid.cell(lambda, active);
        Value x = dr::clip(lambda, mo.grid.lo, mo.grid.hi);
        auto [k, x0, x1] = (mo.joined ? mo.joined->grids : m_grids).cell(mo.grid, x, active);
        return { k, dr::clip((x - x0) / (x1 - x0), 0.f, 1.f), x0, x1 };
    }
    /// Node k of a model's grid (per hero wavelength).
    Wavelength node(const ModelAt &mo, const UInt32W &k, const WaveMask &active) const {
        if (!textured() && !mo.joined)
            return fluo_detail::fetch_each<Wavelength>(m_grid.nodes, k, active);
        return fluo_detail::fetch_each<Wavelength>((mo.joined ? mo.joined->grids : m_grids).nodes, mo.grid.off + k,
                                                   active);
    }

    /// A hit: the models it mixes (uniform: the one; textured: its (radius, density)
    /// corners at the roughness level nearest its alpha, with bilinear weights), its Q, the
    /// elastic lobe's roughness (the hit's own) and the cells of its wavelengths in each
    /// radius corner's grid (spectral, coated, `with_cells`: the elastic lobe's calls, which
    /// also read the substrate's index).
    struct Hit {
        size_t n = 1, per_radius = 1; ///< corners; corner i reads cells[i / per_radius]
        std::array<ModelAt, MaxCorners> model;
        std::array<Float, MaxCorners> weight;
        Float q, alpha;
        std::array<Cells, 2> cells;
        bool has_cells = false;
        dr::Complex<UnpolarizedSpectrum> ior; ///< the substrate's eta + i·k (`with_cells`)
    };

    /// One of a hit's models picked with its weight as probability by u (the first with
    /// u < the running sum of the weights, or the last with a positive weight), its cells,
    /// and u rescaled within its share (uniform again, for reuse).
    struct Pick {
        ModelAt model;
        Cells cells;
        Float u;
    };
    Pick pick(const Hit &h, const Float &u) const {
        Pick p{ h.model[0], h.cells[0], u };
        if (h.n == 1)
            return p;
        Float run = 0.f;
        Mask done = false;
        for (size_t i = 0; i < h.n; ++i) {
            const Float &w = h.weight[i];
            Mask take = !done && w > 0.f;
            p.model = select_model(take, h.model[i], p.model);
            if (h.has_cells)
                p.cells = dr::select(WaveMask(take), h.cells[i / h.per_radius], p.cells);
            p.u = dr::select(take, dr::clip((u - run) / w, 0.f, 1.f), p.u);
            done |= take && u < run + w;
            run += w;
        }
        return p;
    }

    /// jit_choose at a hit (its models' tables: the material's own, or joined ones; spectral
    /// variants: its callers return elastic_only in RGB).
    Choice choose_at(const Hit &h, const SurfaceInteraction3f &si, const Wavelength &u1_, const Wavelength &u2,
                     double range_lo, double range_hi, Mask active) const {
        const Wavelength &lambda_o = si.wavelengths;
        Float cos_i = Frame3f::cos_theta(si.wi);
        // The cells of λo serve the elastic weight and, where λo is below the range's top,
        // the excitation interval's upper end. Fluorescent: coated.
        Wavelength u1 = u1_;
        Pick p = pick(h, u1[0]);
        const ModelAt &mo = p.model;
        Cells cells = cell(mo, lambda_o, active);
        u1[0] = p.u;
        fluo_detail::rotate_hero(u1); // uniform again given the pick
        Emission em = emission_of(mo, active); // with radius's and density's gradients
        // The elastic event's weight: the smooth surface's R_tot from Rust's table (any
        // weight positive where the elastic lobe is keeps the estimator unbiased; this one
        // spares the substrate's eta/k lookups).
        UnpolarizedSpectrum we(
            dr::maximum(bilinear(store(), start(mo, RTot), dr::maximum(cos_i, 0.f), cells, mo, active), 0.f));
        // The excitation interval's ends [a, b] (λi ≤ λo) and their cells: the lights' range
        // within the model's excitation range.
        Float a_r = dr::maximum((float) range_lo, em.ex_lo), hi_r = dr::minimum((float) range_hi, em.ex_hi);
        Cell ca = cell(mo, a_r, active), c_hi = cell(mo, hi_r, active);
        // The A_tot row nearest cos θi (as the Rust model's sampling).
        UInt32 row = UInt32(dr::round(dr::clip(cos_i, 0.f, 1.f) * (float) (m_rows - 1))) * mo.n;
        UInt32 last = mo.n - 1;
        // With gradients on Q, a floor in the shift's weight (at Q = 0 it would never be
        // drawn and dQ of the reradiation Q·e would be lost).
        Float q_choice = dr::detach(h.q);
        if (dr::grad_enabled(h.q))
            q_choice = dr::maximum(q_choice, fluo_detail::GradientShiftFloor);
        // the row's running integral at a: one row and one a for every hero wavelength
        Float c_a = running(mo, row, ca, active && cos_i > 0.f);
        // Per hero wavelength (one packet) the excitation interval [a, b] (λi ≤ λo),
        // e(λo | a) and the row's mass there.
        Wavelength b = dr::minimum(hi_r, lambda_o);
        WaveMask ok = WaveMask(active && cos_i > 0.f) && b > a_r && lambda_o >= em.lmin && lambda_o <= em.lmax;
        Wavelength e_ad = dr::select(ok, emission(lambda_o, em), 0.f), e = dr::detach(e_ad);
        ok &= e > 0.f;
        Cells c_top{ UInt32W(c_hi.k), Wavelength(c_hi.f), Wavelength(c_hi.x0), Wavelength(c_hi.x1) };
        Cells cb = dr::select(lambda_o < hi_r, cells, c_top);
        Wavelength mass = dr::select(ok, dr::maximum(running(mo, row, cb, ok) - c_a, 0.f), 0.f);
        ok &= mass > 0.f;
        fluo_detail::ShiftChoice<UnpolarizedSpectrum> choice(we, q_choice * e * mass, u1, active);
        if constexpr (!dr::is_jit_v<Float>)
            if (dr::none(choice.shifted)) // (scalar variants draw λi only where a shift is taken)
                return { lambda_o, choice.weight(0.f, u1), choice.shifted, 0.f, mo.index, -1.f };
        // λi ∝ the row on [a, b]: the last node whose running integral is ≤ the target,
        // then the cell's quadratic root (cancellation-free form); the search runs over
        // the longest grid, each lane's row clamped to its own.
        Wavelength target = c_a + dr::clip(u2, 0.f, 1.f) * mass;
        const FloatStorage &t = store();
        UInt32 cdf = start(mo, Cdf) + row, a_tot = start(mo, ATot) + row;
        UInt32W k = dr::binary_search<UInt32W>(1, grid_max(mo) - 1, [&](const UInt32W &i) {
                        return fluo_detail::fetch_each<Wavelength>(t, cdf + dr::minimum(i, last), ok) <= target;
                    }) - 1;
        k = dr::clip(k, ca.k, cb.k);
        Wavelength x0 = node(mo, k, ok), x1 = node(mo, k + 1, ok);
        Wavelength f0 = fluo_detail::fetch_each<Wavelength>(t, a_tot + k, ok),
                   f1 = fluo_detail::fetch_each<Wavelength>(t, a_tot + k + 1, ok);
        Wavelength h_ = x1 - x0;
        Wavelength step = fluo_detail::linear_cell_inverse(
            f0, f1, h_, target - fluo_detail::fetch_each<Wavelength>(t, cdf + k, ok));
        Wavelength x = dr::clip(x0 + step, dr::maximum(a_r, x0), dr::minimum(b, x1));
        Wavelength pdf = dr::select(ok, dr::lerp(f0, f1, dr::clip((x - x0) / h_, 0.f, 1.f)) / mass, 0.f);
        UnpolarizedSpectrum scale = choice.weight(pdf, u1);
        const WMask &shifted = choice.shifted;
        // Q·e(λo | λi), nm⁻¹
        return { dr::select(shifted, x, lambda_o), scale, shifted, dr::select(shifted, h.q * e_ad, 0.f),
                 mo.index, -1.f };
    }

    /// jit_reradiation of model `mo` at roughness alpha.
    std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum> reradiation_at(const ModelAt &mo, const Float &alpha,
                                                                       const SurfaceInteraction3f &si,
                                                                       const UnpolarizedSpectrum &rerad,
                                                                       const Vector3f &wo_a, const Vector3f &wo_b,
                                                                       Mask active) const {
        UnpolarizedSpectrum out_a(0.f), out_b(0.f);
        if constexpr (is_spectral_v<Spectrum>) {
            auto [lobe_a, c_a] = lobe(si, wo_a, alpha, active);
            auto [lobe_b, c_b] = lobe(si, wo_b, alpha, active);
            // (at Q = 0 rerad is 0 but carries dQ: every active lane then)
            WaveMask on = WaveMask(active) && (dr::grad_enabled(rerad) ? WaveMask(true) : WaveMask(rerad != 0.f));
            Cells c = cell(mo, si.wavelengths, on);
            out_a = rerad * lobe_a * UnpolarizedSpectrum(bilinear_ad(ATot, &Tangents::a_tot, c_a, c, mo, on));
            out_b = rerad * lobe_b * UnpolarizedSpectrum(bilinear_ad(ATot, &Tangents::a_tot, c_b, c, mo, on));
        } else {
            (void) mo, (void) alpha, (void) si, (void) rerad, (void) wo_a, (void) wo_b, (void) active;
        }
        return { out_a, out_b };
    }

    /// A numeric parameter at si: its texture's value (Mitsuba's own eval_1), else the float.
    Float param(const SurfaceInteraction3f &si, size_t i, const Mask &active) const {
        return m_tex.tex[i] ? m_tex.tex[i]->eval_1(si, active) : Float((float) Tex::field(m_config, i));
    }
    /// The roughness of alpha level i (Mitsuba's clamp of a zero roughness).
    Float level_alpha(const UInt32 &i) const {
        Float a((float) m_tex.alphas[0]);
        for (size_t k = 1; k < m_tex.alphas.size(); ++k)
            a = dr::select(i == (uint32_t) k, m_tex.alphas[k], a);
        return dr::maximum(a, 1e-4f);
    }
    /// The elastic lobe's roughness given the hit's alpha (param()): its own with a textured
    /// alpha (clamped as roughconductor clamps it), else the uniform one.
    Float elastic_alpha(const Float &alpha) const {
        return m_tex.tex[Tex::Alpha] ? dr::maximum(alpha, 1e-4f) : m_alpha_v;
    }

    /// A hit on member `member` of a joined class (its model, Q and roughness; RGB: its rows).
    Hit joined_hit(const JoinedTables &j, const UInt32 &member, const SurfaceInteraction3f &si, const Mask &active,
                   bool with_cells) const {
        Hit h;
        if constexpr (is_spectral_v<Spectrum>)
            h.model[0] = joined_model(j, member, active);
        else
            h.model[0] = { member, UInt32(0), UInt32(0), UInt32(0), GridAt{}, &j };
        h.weight[0] = Float(1.f);
        h.q = fluo_detail::fetch<Float>(j.q, member, active);
        h.alpha = fluo_detail::fetch<Float>(j.alpha, member, active);
        if constexpr (is_spectral_v<Spectrum>) {
            h.has_cells = m_coated && with_cells;
            if (h.has_cells)
                h.cells[0] = cell(h.model[0], si.wavelengths, active);
        }
        if (with_cells)
            h.ior = substrate_ior(si, active);
        return h;
    }

    Hit hit(const SurfaceInteraction3f &si, const Mask &active, bool with_cells) const {
        Hit h;
        if (!textured()) {
            h.model[0] = model_at(UInt32(0), active);
            h.weight[0] = Float(1.f);
            h.q = m_q;
            h.alpha = m_alpha_v;
        } else {
            auto [ri, rt] = fluo_detail::lane_bracket(m_tex.radii, param(si, Tex::Radius, active));
            auto [di, dt] = fluo_detail::lane_bracket(m_tex.densities, param(si, Tex::Density, active));
            Float alpha = param(si, Tex::Alpha, active); // (one texture lookup for both uses)
            UInt32 ai = fluo_detail::lane_nearest(m_tex.alphas, alpha);
            if (m_tex.tex[Tex::Yield]) {
                Float q = m_tex.tex[Tex::Yield]->eval_1(si, active);
                h.q = dr::select(dr::isfinite(q), dr::clip(q, 0.f, 1.f), 0.f);
            } else {
                h.q = m_q; // the float (differentiable)
            }
            h.alpha = elastic_alpha(alpha);
            size_t nr = m_tex.radii.size() > 1 ? 2 : 1, nd = m_tex.densities.size() > 1 ? 2 : 1;
            uint32_t n_density = (uint32_t) m_tex.densities.size(), n_alpha = (uint32_t) m_tex.alphas.size();
            h.n = nr * nd;
            h.per_radius = nd;
            for (size_t a = 0; a < nr; ++a)
                for (size_t b = 0; b < nd; ++b) {
                    UInt32 m = ((ri + (uint32_t) a) * n_density + (di + (uint32_t) b)) * n_alpha + ai;
                    h.model[a * nd + b] = model_at(m, active);
                    h.weight[a * nd + b] = (a ? rt : 1.f - rt) * (b ? dt : 1.f - dt);
                }
        }
        if constexpr (is_spectral_v<Spectrum>) {
            h.has_cells = m_coated && with_cells;
            if (h.has_cells)
                for (size_t a = 0; a * h.per_radius < h.n; ++a)
                    h.cells[a] = cell(h.model[a * h.per_radius], si.wavelengths, active);
        }
        if (with_cells)
            h.ior = substrate_ior(si, active);
        return h;
    }
    /// The substrate's complex index at si (its eta/k textures, as roughconductor's), once
    /// per hit: an eval_pdf_sample's two Fresnel factors share it. Spectral: from m_ior
    /// where it holds the textures' nodes.
    dr::Complex<UnpolarizedSpectrum> substrate_ior(const SurfaceInteraction3f &si, const Mask &active) const {
        if constexpr (is_spectral_v<Spectrum>) {
            if (m_ior.constant)
                return { UnpolarizedSpectrum(m_ior.eta_c), UnpolarizedSpectrum(m_ior.k_c) };
            if (m_ior.tabulated) {
                const Wavelength &lambda = si.wavelengths;
                WaveMask inside = WaveMask(active) && lambda >= m_ior.grid.v_l0 && lambda <= m_ior.grid.v_l1;
                Cells c = m_ior.grid.cell(lambda, inside);
                auto at = [&](const FloatStorage &v) {
                    return UnpolarizedSpectrum(dr::select(
                        inside,
                        dr::lerp(fluo_detail::fetch_each<Wavelength>(v, c.k, inside),
                                 fluo_detail::fetch_each<Wavelength>(v, c.k + 1, inside), c.f),
                        0.f));
                };
                return { at(m_ior.eta), at(m_ior.k) };
            }
        }
        return { m_setup.eta->eval(si, active), m_setup.k->eval(si, active) };
    }

    /// The substrate's eta and k as the spectral variants read them per lane: Mitsuba's
    /// `uniform` spectra as two constants; `irregular` ones on the same nodes (eta and k on
    /// one grid, as Mitsuba's conductor data are) as m_ior's tables, linear between the
    /// nodes and 0 outside them, as the spectra's own eval, but with one bucketed cell
    /// lookup for both (the spectra's eval searches its nodes per texture: that search was
    /// ~0.15 of fluo_qd's per-vertex cost ratio). Anything else is evaluated per lane.
    struct IorTable {
        bool constant = false, tabulated = false;
        Float eta_c = 0.f, k_c = 0.f;
        fluo_detail::LaneGrid<Float> grid;
        FloatStorage eta, k;
    };
    void sync_ior() {
        m_ior = IorTable();
        if constexpr (is_spectral_v<Spectrum>) {
            if (!m_setup.uniform_substrate())
                return;
            struct Nodes {
                std::string_view kind;
                std::vector<float> x, y, value;
            } eta, k;
            for (auto [tex, out] : { std::pair{ m_setup.eta.get(), &eta }, std::pair{ m_setup.k.get(), &k } }) {
                out->kind = tex->class_name();
                auto value = [out = out](std::string_view name, void *v, const std::type_info &type) {
                    if (type == typeid(FloatStorage) && (name == "wavelengths" || name == "values")) {
                        const FloatStorage &b = *static_cast<const FloatStorage *>(v);
                        (name == "wavelengths" ? out->x : out->y) = fluo_detail::host_lanes(b, dr::width(b));
                    } else if (type == typeid(Float) && name == "value") {
                        out->value = { (float) dr::slice(dr::detach(*static_cast<const Float *>(v))) };
                    }
                };
                fluo_detail::visit(tex, value, [](std::string_view, Object *) { return false; });
            }
            if (eta.kind == "UniformSpectrum" && k.kind == "UniformSpectrum" && eta.value.size() == 1 &&
                k.value.size() == 1) {
                m_ior.constant = true;
                m_ior.eta_c = dr::opaque<Float>(eta.value[0]);
                m_ior.k_c = dr::opaque<Float>(k.value[0]);
                return;
            }
            bool ok = eta.kind == "IrregularSpectrum" && k.kind == "IrregularSpectrum" && eta.x.size() >= 2 &&
                      eta.x == k.x && eta.y.size() == eta.x.size() && k.y.size() == k.x.size();
            for (size_t i = 1; ok && i < eta.x.size(); ++i)
                ok = eta.x[i] > eta.x[i - 1];
            if (!ok)
                return;
            m_ior.grid.set(std::vector<double>(eta.x.begin(), eta.x.end()));
            m_ior.eta = dr::load<FloatStorage>(eta.y.data(), eta.y.size());
            m_ior.k = dr::load<FloatStorage>(k.y.data(), k.y.size());
            m_ior.tabulated = true;
        }
    }

    /// The microfacet lobe D G/(4 cos θi) at roughness alpha, and cos θ = ωi·h.
    std::pair<Float, Float> lobe(const SurfaceInteraction3f &si, const Vector3f &wo, const Float &alpha,
                                 Mask active) const {
        Float cos_i = Frame3f::cos_theta(si.wi);
        Vector3f h = dr::normalize(wo + si.wi);
        MicrofacetDistribution distr(m_type, alpha, alpha, true);
        Float g = distr.smith_g1(si.wi, h) * distr.smith_g1(wo, h), c = dr::minimum(dr::dot(si.wi, h), 1.f);
        Float value = distr.eval(h) * g / (4.f * cos_i);
        active &= cos_i > 0.f && Frame3f::cos_theta(wo) > 0.f && g > 0.f && c > 0.f && dr::isfinite(value);
        return { dr::select(active, value, 0.f), dr::select(active, c, 0.f) };
    }

    std::pair<BSDFSample3f, Spectrum> sample_with(const BSDFContext &ctx, const SurfaceInteraction3f &si,
                                                  const Point2f &sample2, Mask active, const Hit &h) const {
        BSDFSample3f bs = dr::zeros<BSDFSample3f>();
        Float cos_theta_i = Frame3f::cos_theta(si.wi);
        active &= cos_theta_i > 0.f;
        if (unlikely(!ctx.is_enabled(BSDFFlags::GlossyReflection) || dr::none_or<false>(active)))
            return { bs, 0.f };
        MicrofacetDistribution distr(m_type, h.alpha, h.alpha, true);
        auto [m, pdf] = distr.sample(si.wi, sample2);
        bs.wo = reflect(si.wi, m);
        bs.eta = 1.f;
        bs.sampled_component = 0;
        bs.sampled_type = +BSDFFlags::GlossyReflection;
        active &= (pdf != 0.f) && Frame3f::cos_theta(bs.wo) > 0.f;
        bs.pdf = dr::select(active, pdf / (4.f * dr::dot(bs.wo, m)), 0.f);
        UnpolarizedSpectrum weight = distr.smith_g1(bs.wo, m) * fresnel_value(si, dr::dot(si.wi, m), active, h);
        return { bs, lobe_spectrum(ctx, si, bs.wo, m, weight, active, h) };
    }

    /// The elastic lobe's `value` as Mitsuba's Spectrum: in the polarized variants the
    /// substrate's Mueller matrix for specular reflection off the microfacet `m` (the
    /// conductor's complex index, the matrix rotated into the Stokes bases of the light's
    /// incoming and outgoing directions, as `roughconductor` does), scaled so that its
    /// intensity is `value`: the coating's tables are averaged over polarization, so the
    /// coating scales the substrate's matrix (exact without a coating); elsewhere the value.
    Spectrum lobe_spectrum(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
                           const Vector3f &m, const UnpolarizedSpectrum &value, const Mask &active, const Hit &h) const {
        if constexpr (is_polarized_v<Spectrum>) {
            const dr::Complex<UnpolarizedSpectrum> &eta_c = h.ior;
            // Light arrives along −w_in and leaves along w_out.
            bool radiance = ctx.mode == TransportMode::Radiance;
            Vector3f w_in = radiance ? wo : si.wi, w_out = radiance ? si.wi : wo;
            Spectrum F = mueller::specular_reflection(UnpolarizedSpectrum(dr::dot(w_in, m)), eta_c);
            Vector3f s_in = dr::cross(m, -w_in), s_out = dr::cross(m, w_out);
            Mask collinear = dr::all(s_in == Vector3f(0.f));
            s_in = dr::select(collinear, Vector3f(1.f, 0.f, 0.f), dr::normalize(s_in));
            s_out = dr::select(collinear, Vector3f(1.f, 0.f, 0.f), dr::normalize(s_out));
            F = mueller::rotate_mueller_basis(F, -w_in, s_in, mueller::stokes_basis(-w_in), w_out, s_out,
                                              mueller::stokes_basis(w_out));
            UnpolarizedSpectrum f0 = F(0, 0);
            return (F * dr::select(f0 > 0.f, value / f0, 0.f)) & active;
        } else {
            (void) ctx, (void) wo, (void) m, (void) h;
            return depolarizer<Spectrum>(dr::select(active, value, 0.f));
        }
    }

    std::pair<Spectrum, Float> eval_pdf_with(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
                                             Mask active, const Hit &h) const {
        Float cos_theta_i = Frame3f::cos_theta(si.wi), cos_theta_o = Frame3f::cos_theta(wo);
        Vector3f H = dr::normalize(wo + si.wi);
        active &= cos_theta_i > 0.f && cos_theta_o > 0.f && dr::dot(si.wi, H) > 0.f && dr::dot(wo, H) > 0.f;
        if (unlikely(!ctx.is_enabled(BSDFFlags::GlossyReflection) || dr::none_or<false>(active)))
            return { 0.f, 0.f };
        MicrofacetDistribution distr(m_type, h.alpha, h.alpha, true);
        Float D = distr.eval(H), smith_g1_wi = distr.smith_g1(si.wi, H);
        Float G = smith_g1_wi * distr.smith_g1(wo, H);
        UnpolarizedSpectrum value = fresnel_value(si, dr::dot(si.wi, H), active, h) * (D * G / (4.f * cos_theta_i));
        Float pdf = D * smith_g1_wi / (4.f * cos_theta_i);
        return { lobe_spectrum(ctx, si, wo, H, value, active, h), dr::select(active, pdf, 0.f) };
    }
    /// A table's row (offset `row`) at the cell, linear in λ.
    template <typename Value>
    Value along(const FloatStorage &t, const UInt32 &row, const CellOf<Value> &c, const dr::mask_t<Value> &active) const {
        return dr::lerp(fluo_detail::fetch_each<Value>(t, row + c.k, active),
                        fluo_detail::fetch_each<Value>(t, row + c.k + 1, active), c.f);
    }
    /// The running integral of row `row` (its offset in a table) of A_tot up to the cell's λ.
    template <typename Value>
    Value running(const ModelAt &mo, const UInt32 &row, const CellOf<Value> &c, const dr::mask_t<Value> &active) const {
        const FloatStorage &t = store();
        dr::uint32_array_t<Value> a_tot = start(mo, ATot) + row + c.k;
        Value f0 = fluo_detail::fetch_each<Value>(t, a_tot, active), f1 = fluo_detail::fetch_each<Value>(t, a_tot + 1, active);
        Value half = .5f * c.f * (c.x1 - c.x0);
        return fluo_detail::fetch_each<Value>(t, start(mo, Cdf) + row + c.k, active) + half * (f0 + dr::lerp(f0, f1, c.f));
    }
    /// Rows j, j + 1 around cos θ and the fraction between them.
    std::pair<UInt32, Float> rows_at(const Float &cos_theta) const {
        Float x = dr::clip(cos_theta, 0.f, 1.f) * (float) (m_rows - 1);
        UInt32 j = dr::minimum(UInt32(dr::floor(x)), m_rows - 2);
        return { j, x - Float(j) };
    }
    /// A model's [rows][λ] table (in `t` at `base`), bilinear in (cos θ, λ).
    template <typename Value>
    Value bilinear(const FloatStorage &t, const UInt32 &base, const Float &cos_theta, const CellOf<Value> &c,
                   const ModelAt &mo, const dr::mask_t<Value> &active) const {
        auto [j, fc] = rows_at(cos_theta);
        UInt32 r0 = base + j * mo.n;
        return dr::lerp(along(t, r0, c, active), along(t, r0 + mo.n, c, active), fc);
    }
    /// Spectral, uniform material: the tables' derivatives in radius (p = 0) and density
    /// (p = 1), central differences of the tables Rust bakes at the parameter ± h on this
    /// model's λ grid (one-sided where ± h leaves the valid range), and of the emission's
    /// peak, scale and 1/normalisation. Built once per build when either carries a gradient:
    /// in parameters_changed (an update after enabling it), else when a render first asks
    /// (from the substrate's spectra kept at the build: no texture is evaluated while the
    /// integrator traces). A value then carries value + (θ − detach(θ))·∂value/∂θ: the same
    /// value, and its derivative for AD. Sampling stays detached.
    struct Tangents {
        uint64_t build = 0;
        std::array<FloatStorage, 2> a_tot, r_spe, pass, rgb_rows;
        std::array<float, 2> peak{}, scale{}, inv_norm{};
    };
    static constexpr double TangentStep[2] = { 1e-3, 1e-3 }; ///< h: radius (nm), density

    /// The tangents where radius or density carry gradients (else null).
    const Tangents *tangents() const {
        if (textured() || !(wants(0) || wants(1)))
            return nullptr;
        if (m_tangents.build != m_build)
            bake_tangents();
        return &m_tangents;
    }
    /// Whether radius (p = 0) or density (p = 1) carries a gradient.
    bool wants(size_t p) const { return dr::grad_enabled(p == 0 ? m_radius : m_density); }
    /// θ − detach(θ) of radius (p = 0) or density (p = 1): 0 with θ's gradient.
    Float delta(size_t p) const {
        const Float &v = p == 0 ? m_radius : m_density;
        return v - dr::detach(v);
    }

    void bake_tangents() const {
        const fluo_detail::QdSamples &eta = m_samples[0], &k = m_samples[1], &qd_eta = m_samples[2],
                                     &qd_k = m_samples[3];
        rust::Slice<const double> grid(m_grid.host.data(), m_grid.host.size());
        Tangents t;
        for (size_t p = 0; p < 2; ++p) {
            // the tables at θ + s·h for s = ±1, or θ where that is out of range
            auto at = [&](double sign, double &x) -> std::optional<fluo::QdJitTables> {
                fluo::QdConfig c = m_config;
                double &field = p == 0 ? c.radius : c.density;
                x = field + sign * TangentStep[p];
                field = x;
                try {
                    rust::Box<fluo::QdModel> m = fluo::qd_new(c, eta.view(), k.view(), qd_eta.view(), qd_k.view());
                    // (RGB: the channels' tables alone, as rebuild())
                    return fluo::qd_jit_tables(*m, JitCosNodes,
                                               is_spectral_v<Spectrum> ? grid : rust::Slice<const double>(),
                                               rust::Slice<const double>(Setup::RgbWavelengths, 3),
                                               is_spectral_v<Spectrum>);
                } catch (const std::exception &) {
                    return std::nullopt;
                }
            };
            double x_hi = 0.0, x_lo = 0.0;
            std::optional<fluo::QdJitTables> hi = at(1.0, x_hi), lo = at(-1.0, x_lo);
            if (!hi)
                hi = at(0.0, x_hi);
            if (!lo)
                lo = at(0.0, x_lo);
            if (!hi || !lo || !(x_hi > x_lo))
                Throw("%s: no derivative tables in \"%s\" at %f", Plugin, p == 0 ? "radius" : "density",
                      p == 0 ? m_config.radius : m_config.density);
            double inv = 1.0 / (x_hi - x_lo);
            auto diff = [&](const auto &a, const auto &b) {
                std::vector<float> d(a.size());
                for (size_t i = 0; i < a.size(); ++i)
                    d[i] = (float) ((a[i] - b[i]) * inv);
                return dr::load<FloatStorage>(d.data(), d.size());
            };
            if constexpr (is_spectral_v<Spectrum>) {
                t.a_tot[p] = diff(hi->a_tot, lo->a_tot);
                t.r_spe[p] = diff(hi->r_spe, lo->r_spe);
                t.pass[p] = diff(hi->pass, lo->pass);
            } else {
                t.rgb_rows[p] = diff(rgb_cells(hi->extra_r_spe, hi->extra_pass), rgb_cells(lo->extra_r_spe, lo->extra_pass));
            }
            auto inv_norm = [](const fluo::QdJitTables &x) { return x.emission_norm > 0.0 ? 1.0 / x.emission_norm : 0.0; };
            t.peak[p] = (float) ((hi->emission_peak_nm - lo->emission_peak_nm) * inv);
            t.scale[p] = (float) ((hi->emission_scale_nm - lo->emission_scale_nm) * inv);
            t.inv_norm[p] = (float) ((inv_norm(*hi) - inv_norm(*lo)) * inv);
        }
        t.build = m_build;
        m_tangents = std::move(t);
    }

    /// bilinear() of table k, plus its tangents (with_tangents).
    template <typename Value>
    Value bilinear_ad(Table k, std::array<FloatStorage, 2> Tangents::*table, const Float &cos_theta,
                      const CellOf<Value> &c, const ModelAt &mo, const dr::mask_t<Value> &active) const {
        return with_tangents(bilinear(store(), start(mo, k), cos_theta, c, mo, active), table, cos_theta, c, mo,
                             active);
    }
    /// v plus the tangents' (θ − detach(θ))·∂/∂θ at (cos θ, the cell) where radius or density
    /// carry gradients (`table`: which of Tangents' arrays, [rows][n] each).
    template <typename Out, typename Value>
    Out with_tangents(Out v, std::array<FloatStorage, 2> Tangents::*table, const Float &cos_theta,
                      const CellOf<Value> &c, const ModelAt &mo, const dr::mask_t<Value> &active) const {
        if (const Tangents *tg = mo.joined ? nullptr : tangents())
            for (size_t p = 0; p < 2; ++p)
                if (wants(p))
                    v = dr::fmadd(Out(delta(p)), Out(bilinear((tg->*table)[p], UInt32(0), cos_theta, c, mo, active)), v);
        return v;
    }

    /// Model mo's R_spe and pass at (cos θ, the cell), bilinear as bilinear(). The block
    /// begins with 4 floats per entry e of their rows, [R_spe(e), pass(e), R_spe(e + 1),
    /// pass(e + 1)]: one read per row (a packet gather in the JIT variants; single reads were
    /// ~0.2 of the per-vertex ratio); a block starts at a multiple of 4, a textured
    /// material's model mo at 4 times its place in the other tables.
    std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum> film(const Float &cos_theta, const Cells &c, const ModelAt &mo,
                                                             const WaveMask &active) const {
        auto [j, fc] = rows_at(cos_theta);
        UInt32 row = (mo.off + (mo.joined ? UInt32(0) : 3 * (mo.off - m_tables.offset()))) / 4 + j * mo.n;
        auto v0 = fluo_detail::fetch_packet<4, 4, Wavelength>(store(), row + c.k, active),
             v1 = fluo_detail::fetch_packet<4, 4, Wavelength>(store(), row + mo.n + c.k, active);
        auto at = [&](size_t e) {
            return UnpolarizedSpectrum(dr::lerp(dr::lerp(v0[e], v0[e + 2], c.f), dr::lerp(v1[e], v1[e + 2], c.f), fc));
        };
        return { at(0), at(1) };
    }

    /// RGB: a model's R_spe and pass at cos θ, per channel, from its rows in `t`
    /// ([model][rows][8]: the channels' R_spe, their pass, 2 of padding; rgb_cells), one
    /// packet read per row.
    std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum> rgb_rows(const FloatStorage &t, const Float &cos_theta,
                                                                 const ModelAt &mo, const Mask &active) const {
        auto [j, fc] = rows_at(cos_theta);
        UInt32 row = mo.index * m_rows + j;
        auto a = fluo_detail::fetch_packet<8, 6, Float>(t, row, active),
             b = fluo_detail::fetch_packet<8, 6, Float>(t, row + 1, active);
        UnpolarizedSpectrum r_spe, pass;
        for (size_t ch = 0; ch < 3; ++ch) {
            r_spe[ch] = dr::lerp(a[ch], b[ch], fc);
            pass[ch] = dr::lerp(a[3 + ch], b[3 + ch], fc);
        }
        return { r_spe, pass };
    }
    /// A model's channel rows of R_spe and pass ([rows][3] each, Rust's) as rgb_rows reads them.
    template <typename Rows> static std::vector<double> rgb_cells(const Rows &r_spe, const Rows &pass) {
        std::vector<double> out(r_spe.size() / 3 * 8, 0.0);
        for (size_t i = 0; i < r_spe.size(); ++i) {
            out[i / 3 * 8 + i % 3] = r_spe[i];
            out[i / 3 * 8 + 3 + i % 3] = pass[i];
        }
        return out;
    }

    /// A model's logistic emission: peak, scale, 1/normalisation, the range where it is
    /// defined and the excitation range (uniform: constants; textured: per lane).
    struct Emission {
        Float peak, scale, inv_norm, lmin, lmax, ex_lo, ex_hi;
    };
    Emission emission_of(const ModelAt &mo, const Mask &active) const {
        if (!textured() && !mo.joined) {
            Emission e{ m_em[0], m_em[1], m_em[2], m_em[3], m_em[4], m_em[5], m_em[6] };
            if (const Tangents *t = tangents())
                for (size_t p = 0; p < 2; ++p) {
                    if (!wants(p))
                        continue;
                    Float d = delta(p);
                    e.peak = dr::fmadd(d, t->peak[p], e.peak);
                    e.scale = dr::fmadd(d, t->scale[p], e.scale);
                    e.inv_norm = dr::fmadd(d, t->inv_norm[p], e.inv_norm);
                }
            return e;
        }
        Emission e;
        Float *fields[EmissionFields] = { &e.peak, &e.scale, &e.inv_norm, &e.lmin, &e.lmax, &e.ex_lo, &e.ex_hi };
        for (uint32_t i = 0; i < EmissionFields; ++i)
            *fields[i] = fluo_detail::fetch<Float>(mo.joined ? mo.joined->emission : m_emission, mo.index * EmissionFields + i,
                                           active);
        return e;
    }
    static constexpr uint32_t EmissionFields = 7;

    /// e(λo | λi) = L(λo)/I (λo > λi, within [λmin, λmax], checked by the caller): the
    /// logistic density exp(−|u|)/(s(1 + exp(−|u|))²), u = (λo − peak)/s, as band.rs.
    template <typename Value> static Value emission(const Value &lambda_o, const Emission &em) {
        Value e = dr::exp(-dr::abs((lambda_o - em.peak) / em.scale));
        return e / (em.scale * dr::square(1.f + e)) * em.inv_norm;
    }

    /// The substrate's Fresnel factor F (its eta/k textures, as roughconductor), and with a
    /// coating R_tot = R_spe + pass·F/(1 − F·R_spe) (eq. 23); textured: the hit's models'
    /// values mixed with their weights.
    UnpolarizedSpectrum fresnel_value(const SurfaceInteraction3f &si, const Float &cos_m, const Mask &active,
                                      const Hit &h) const {
        UnpolarizedSpectrum F = fresnel_conductor(UnpolarizedSpectrum(cos_m), h.ior);
        if (!m_coated)
            return F;
        UnpolarizedSpectrum mixed(0.f);
        for (size_t i = 0; i < h.n; ++i) {
            Mask on = active && h.weight[i] > 0.f;
            if constexpr (!dr::is_jit_v<Float>)
                if (!on) // (scalar: a corner without weight, e.g. a texture at a level, adds nothing)
                    continue;
            UnpolarizedSpectrum r_spe, pass;
            if constexpr (is_spectral_v<Spectrum>) {
                const Cells &c = h.cells[i / h.per_radius];
                std::tie(r_spe, pass) = film(cos_m, c, h.model[i], WaveMask(on));
                r_spe = with_tangents(r_spe, &Tangents::r_spe, cos_m, c, h.model[i], WaveMask(on));
                pass = with_tangents(pass, &Tangents::pass, cos_m, c, h.model[i], WaveMask(on));
            } else {
                const JoinedTables *j = h.model[i].joined;
                std::tie(r_spe, pass) = rgb_rows(j ? j->rgb_rows : m_rgb_rows, cos_m, h.model[i], on);
                if (const Tangents *tg = tangents())
                    for (size_t p = 0; p < 2; ++p)
                        if (wants(p)) {
                            auto [d_spe, d_pass] = rgb_rows(tg->rgb_rows[p], cos_m, h.model[i], on);
                            r_spe += delta(p) * d_spe;
                            pass += delta(p) * d_pass;
                        }
            }
            UnpolarizedSpectrum v = r_spe + pass * F / dr::maximum(1.f - F * r_spe, 1e-12f);
            mixed = h.n == 1 ? v : dr::fmadd(h.weight[i], v, mixed);
        }
        return mixed;
    }

    /// A model's reduced reradiation at the microfacet cosines as MaxTerms terms per unit Q:
    /// B_t into `basis` ([MaxTerms][kk]) and their weights at the nodes into `nodes`
    /// ([n][MaxTerms]); returns n, and the truncation's error (of the largest entry) in
    /// `error`. `q`: the model's own Q (its tables scale with it).
    size_t reduce_nodes(const fluo::QdModel &model, double q, const fluo::TransportBasis &transport, size_t kk,
                        std::vector<double> &basis, std::vector<double> &nodes, double &error) const {
        size_t n = fluo::reduced_microfacet_nodes();
        basis.assign(MaxTerms * kk, 0.0);
        nodes.assign(n * MaxTerms, 0.0);
        auto reduced = fluo::reduced_new(fluo::qd_fluorescence(model), transport);
        error = fluo::reduced_microfacet_low_rank(*reduced, MaxTerms, rust::Slice<double>(basis.data(), basis.size()),
                                                  rust::Slice<double>(nodes.data(), nodes.size()));
        if (!(error >= 0.0) || !std::isfinite(error))
            Throw("%s: no microfacet reduced operator", Plugin);
        for (double &v : basis)
            v /= q; // fluorescent: Q > 0
        return n;
    }

    /// A warning where MaxTerms terms hold a reduction (a textured material: its worst model)
    /// less well than expected: once per process, and again only for one at least twice as
    /// far off as the last reported (200 coatings print a line or two, not 200).
    static void warn_low_rank(double error, const char *what) {
        static std::atomic<double> reported{ 0.0 };
        double last = reported.load();
        if (error > WarnLowRank && error > 2.0 * last && reported.compare_exchange_strong(last, error))
            Log(Warn, "%s: the reduced reradiation of %s is held by %zu terms to %.2g of its largest entry "
                      "(expected below %.2g): RGB renders may be off by about that much (further coatings "
                      "held less well are reported only when twice as far off)", Plugin, what, MaxTerms,
                error, WarnLowRank);
    }
    /// Truncation error above which warn_low_rank speaks: ten times Rust's rank tolerance
    /// (basis "auto", whose light band is the lamps' own shape, holds some coatings to
    /// 6e-5, invisible in a render).
    static constexpr double WarnLowRank = 1e-4;

    /// Validate the configuration in Rust, build the model (textured: one per level triple)
    /// and bake the tables.
    void rebuild() {
        fluo_detail::QdSamples eta, k, qd_eta, qd_k; // qd_eta, qd_k empty: built-in CdSe
        m_setup.sample_all(m_config, eta, k, qd_eta, qd_k);
        m_tex.bake(m_config, eta, k, qd_eta, qd_k); // textured: m_config takes the largest levels
        m_samples = { eta, k, qd_eta, qd_k };       // (sampled once: the tangents reuse them)
        sync_ior();
        rust::Box<fluo::QdModel> model = fluo_detail::rust_call(Plugin, [&] {
            return fluo::qd_new(m_config, eta.view(), k.view(), qd_eta.view(), qd_k.view());
        });
        // (asked of a varying substrate alone: the question bakes the Rust model's own tables,
        // which the renderer's tables below do without)
        if (!m_setup.uniform_substrate() && (textured() ? m_tex.fluoresces : fluo::qd_is_fluorescent(*model)))
            Throw("%s: a spatially varying substrate (textured \"eta\"/\"k\") cannot be combined "
                  "with a fluorescent coating: the coating's absorption tables are baked for one "
                  "substrate (the elastic part alone is evaluated per hit); give constant "
                  "\"eta\"/\"k\", or \"density\" = 0 or \"quantum_yield\" = 0",
                  Plugin);
        m_unit.reset();
        if (!textured() && m_config.quantum_yield == 0.0 && m_config.density > 0.0 && m_setup.uniform_substrate()) {
            fluo::QdConfig unit = m_config;
            unit.quantum_yield = 1.0;
            m_unit = fluo_detail::rust_call(Plugin, [&] {
                return fluo::qd_new(unit, eta.view(), k.view(), qd_eta.view(), qd_k.view());
            });
        }
        std::vector<const fluo::QdModel *> models;
        if (textured())
            for (const auto &m : m_tex.models)
                models.push_back(&*m);
        else
            models.push_back(m_unit ? &**m_unit : &*model);
        std::array<std::vector<float>, Tables> tables; // (spectral)
        std::vector<float> rgb, emission;
        std::vector<uint32_t> t_off;
        m_grids = fluo_detail::LaneGridSet<Float>();
        for (const fluo::QdModel *m : models) {
            fluo::QdJitTables t =
                fluo::qd_jit_tables(*m, JitCosNodes, {}, rust::Slice<const double>(Setup::RgbWavelengths, 3),
                                    is_spectral_v<Spectrum>); // (RGB: the channels' tables alone)
            if (t.lambda.size() < 2 || t.rows < 2)
                Throw("%s: the coating's tables have %zu wavelengths and %zu rows (at least 2 each expected)",
                      Plugin, t.lambda.size(), t.rows);
            m_rows = (uint32_t) t.rows;
            t_off.push_back((uint32_t) tables[ATot].size());
            for (auto [dst, src] : { std::pair{ &tables[ATot], &t.a_tot }, std::pair{ &tables[Cdf], &t.cdf },
                                     std::pair{ &tables[RSpe], &t.r_spe }, std::pair{ &tables[Pass], &t.pass },
                                     std::pair{ &tables[RTot], &t.r_tot } })
                dst->insert(dst->end(), src->begin(), src->end());
            std::vector<double> cells = rgb_cells(t.extra_r_spe, t.extra_pass);
            rgb.insert(rgb.end(), cells.begin(), cells.end());
            for (double v : { t.emission_peak_nm, t.emission_scale_nm,
                              t.emission_norm > 0.0 ? 1.0 / t.emission_norm : 0.0, t.lambda_min, t.lambda_max,
                              t.excitation_lo, t.excitation_hi })
                emission.push_back((float) v);
            if (textured())
                m_grids.add(t.lambda, true);
            else
                m_grid.set(std::vector<double>(t.lambda.begin(), t.lambda.end()));
        }
        // A hit finds its λ cells once per radius (Hit::cells): every model of one radius
        // must share its grid (Rust's grid depends on the band, i.e. on the radius, alone).
        for (size_t m = 0, per_radius = m_tex.densities.size() * m_tex.alphas.size(); textured() && m < models.size();
             ++m) {
            size_t first = m - m % per_radius;
            if (m_grids.n[m] != m_grids.n[first] ||
                !std::equal(m_grids.host.begin() + m_grids.off[m], m_grids.host.begin() + m_grids.off[m] + m_grids.n[m],
                            m_grids.host.begin() + m_grids.off[first]))
                Throw("%s: the coatings of one radius have different wavelength grids (models %zu and %zu)", Plugin,
                      first, m);
        }
        if (textured()) {
            m_grids.upload();
            m_t_off = dr::load<UInt32Storage>(t_off.data(), t_off.size());
        }
        m_model = std::move(model);
        // only the tables this variant reads (the RGB ones evaluate R_spe and pass at the
        // channels' wavelengths; 1.4 MB of spectral tables per material spared there), the
        // spectral ones in the table store, one after the other
        if constexpr (is_spectral_v<Spectrum>) {
            m_len = (uint32_t) tables[ATot].size();
            // (film()'s 4 floats per entry, then A_tot, its integral, R_tot; a length that is a
            // multiple of 4, so that every block of the store starts at a multiple of 4)
            std::vector<float> block((7 * m_len + 3) / 4 * 4, 0.f);
            for (uint32_t e = 0; e < m_len; ++e) {
                for (uint32_t h = 0; h < 2 && e + h < m_len; ++h)
                    for (uint32_t k : { RSpe, Pass })
                        block[4 * e + 2 * h + k - RSpe] = tables[k][e + h];
                for (uint32_t k : { ATot, Cdf, RTot })
                    block[(4 + k) * m_len + e] = tables[k][e];
            }
            m_tables.assign(block);
            if (m_tables.at() % 4 != 0)
                Throw("%s: internal error: the coating's tables start at %u, not a multiple of 4", Plugin,
                      m_tables.at());
            m_len_v = dr::opaque<UInt32>(m_len);
        } else {
            m_rgb_rows = fluo_detail::load_floats<FloatStorage>(rgb);
        }
        m_emission = fluo_detail::load_floats<FloatStorage>(emission);
        // uniform: the model's emission and roughness (Mitsuba's own clamp of a zero one) as
        // values of the kernel, not literals: instances differing in them share one callable
        for (size_t i = 0; i < 7; ++i)
            m_em[i] = emission[i];
        m_alpha_v = dr::maximum((ScalarFloat) m_config.alpha, (ScalarFloat) 1e-4f);
        dr::make_opaque(m_em[0], m_em[1], m_em[2], m_em[3], m_em[4], m_em[5], m_em[6], m_alpha_v, m_q, m_radius,
                        m_density);
        m_coated = m_config.density > 0.0; // textured: the largest density level
        static std::atomic<uint64_t> builds{ 0 };
        m_build = ++builds;
    }

    /// The parameters a texture may replace, as (Tex index, member), in traversal order.
    std::array<std::pair<size_t, Float *>, 4> params() {
        return { { { Tex::Yield, &m_q }, { Tex::Radius, &m_radius }, { Tex::Density, &m_density },
                   { Tex::Alpha, &m_alpha } } };
    }

    /// The traversed members from the configuration (at load).
    void sync_members() {
        for (auto [i, value] : params())
            *value = (ScalarFloat) Tex::field(m_config, i);
        m_width = (ScalarFloat) m_config.width;
        dr::make_opaque(m_q, m_radius, m_density, m_alpha); // (see rebuild())
    }

    fluo::QdConfig m_config = fluo::qd_default_config(); ///< the defaults live in Rust (QdParams)
    fluo_detail::UpdateRecord<Float> m_record; ///< the traversed values, as last accepted
    std::optional<rust::Box<fluo::QdModel>> m_model; ///< textured: at the largest levels (a representative)
    std::optional<rust::Box<fluo::QdModel>> m_unit;  ///< see baked()
    Setup m_setup;
    Tex m_tex; ///< textured radius, density, quantum_yield, alpha: textures, levels, baked models
    MicrofacetType m_type = MicrofacetType::Beckmann;
    Float m_alpha_v = 0.1f; ///< the roughness (uniform material)
    bool m_coated = false;
    /// the tables ([rows][λ] row major per model, the models' blocks concatenated at m_t_off;
    /// RGB ones [model][rows][3]) and their grids (uniform: m_grid; textured: m_grids)
    typename fluo_detail::TableStore<Float>::Block m_tables; ///< spectral: the Tables, each m_len long (film())
    uint32_t m_len = 0;
    UInt32 m_len_v = 0; ///< m_len, opaque
    FloatStorage m_rgb_rows; ///< RGB: the channels' R_spe and pass per model and row (rgb_rows())
    FloatStorage m_emission; ///< [model][EmissionFields] (textured)
    UInt32Storage m_t_off;   ///< each model's table offset (textured)
    uint32_t m_rows = 2; ///< the tables' rows (cosine nodes)
    mutable std::shared_ptr<const JoinedTables> m_joined; ///< the last tables this material joined
    /// this build, numbered across all materials (no two builds share one, even where a new
    /// material reuses a freed one's address): keys the reductions below, the tangents and
    /// the joined tables (jit_join)
    uint64_t m_build = 0;
    mutable Tangents m_tangents; ///< the spectral tables' derivatives (tangents())
    std::array<fluo_detail::QdSamples, 4> m_samples; ///< eta, k, qd_eta, qd_k as Rust got them
    IorTable m_ior; ///< the substrate's eta/k as the spectral variants read them (sync_ior)
    // the reduced operator of the last basis fluo_path asked for (jit_reduced_nodes), and
    // every textured model's (jit_reduced_nodes_table)
    mutable std::string m_reduced_key, m_table_key;
    mutable std::array<std::vector<double>, MaxTerms> m_reduced_m;
    mutable std::vector<double> m_reduced_nodes, m_table_m, m_table_nodes;
    mutable size_t m_reduced_n = 0, m_table_n = 0;
    fluo_detail::LaneGrid<Float> m_grid; ///< a uniform material's λ grid (its uniform segments)
    fluo_detail::LaneGridSet<Float> m_grids; ///< the textured models' λ grids
    /// a uniform material's emission: peak, scale, 1/normalisation, lmin, lmax, ex_lo, ex_hi
    Float m_em[7];
    Float m_q = 0.f; ///< Q (differentiable)
    Float m_radius = 0.f, m_density = 0.f; ///< differentiable in the spectral variants (uniform material)
    Float m_alpha = 0.f; ///< the traversed roughness (differentiable, uniform material; m_alpha_v follows it)
    ScalarFloat m_width = 0.f;

    MI_TRAVERSE_CB(Base, m_grid.nodes, m_grid.buckets, m_grids.nodes, m_grids.d_ends, m_grids.d_size, m_grids.buckets,
                   m_rgb_rows, m_emission, m_t_off, m_q, m_ior.grid.nodes, m_ior.grid.buckets, m_ior.eta,
                   m_ior.k)
};

static const bool fluo_qd_jit_registered =
    (fluo_detail::register_plugin<FluoQd>("fluo_qd", ObjectType::BSDF), true);

NAMESPACE_END(mitsuba)
