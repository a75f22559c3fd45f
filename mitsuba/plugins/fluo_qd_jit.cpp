// fluo_qd in the vectorised variants (llvm_ad_rgb, llvm_ad_spectral and the cuda ones). The
// plugin's documentation, and the reference implementation the tests hold this one against,
// are in fluo_qd.cpp; what differs here is said there under "Vectorised variants".
//
// Rust validates the parameters, builds the coating model and bakes, at load and in
// parameters_changed(), what the shim interpolates per lane (fluo::qd_jit_tables): on the
// model's λ grid and JitCosNodes cosines, A_tot (the reradiation's absorption) with its running
// integral along λ, and the coating's R_spe and pass = (T_spe (1 − A_tf))²; bilinear in
// (cos θ, λ) they stay within 7e-4 of A_tot's peak and 1.3e-4 of R_spe and pass (Rust test
// jit_tables_interpolate_the_model). Per lane the shim evaluates with Dr.Jit types:
// - the elastic lobe: Mitsuba's microfacet distribution (as roughconductor) with the Fresnel
//   factor R_tot = R_spe + pass·F/(1 − F·R_spe) over the substrate's own F (its eta/k
//   textures); RGB variants take R_spe and pass at the channels' wavelengths, as fluo_qd.cpp.
// - the shift (spectral): λi | λo sampled ∝ the A_tot row nearest cos θi on the excitation
//   interval (its CDF inverted exactly, the cell's quadratic root), weighted by the logistic
//   emission e(λo | λi) = L(λo)/I and Q; the reradiation towards ωo is
//   D G/(4 cos θi)·Q·A_tot(ωi·h, λi)·e(λo | λi).
// - RGB: Rust's reduced reradiation matrices at the microfacet cosines (the scalar fluo_path's),
//   as a few terms s_t(cos θ)·B_t (a truncated SVD, within 1e-5), scaled by the lobe.
#include <mitsuba/core/properties.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/fresnel.h>
#include <mitsuba/render/microfacet.h>
#include <mitsuba/render/texture.h>

#include <algorithm>
#include <optional>
#include <string>
#include <vector>

#include "fluo_common.h"
#include "fluo_jit.h"
#include "fluo_qd_setup.h"

NAMESPACE_BEGIN(mitsuba)

template <typename Float, typename Spectrum>
class FluoQdJit final : public BSDF<Float, Spectrum>, public fluo_detail::JitBispectral<Float, Spectrum> {
public:
    MI_IMPORT_BASE(BSDF, m_flags, m_components)
    MI_IMPORT_TYPES(Texture, MicrofacetDistribution)
    using WMask = dr::mask_t<UnpolarizedSpectrum>;
    using FloatStorage = DynamicBuffer<Float>;
    using Setup = fluo_detail::QdSetup<Float, Spectrum>;
    using fluo_detail::JitBispectral<Float, Spectrum>::MaxTerms;
    using Choice = typename fluo_detail::JitBispectral<Float, Spectrum>::Choice;

    static constexpr const char *Plugin = "fluo_qd";
    /// Rows of the interpolated tables, uniform in cos θ (the Rust test measures the error at
    /// this many; 4·129·~530 floats per table).
    static constexpr size_t JitCosNodes = 129;

    FluoQdJit(const Properties &props) : Base(props) {
        for (const char *name : { "radius", "density", "quantum_yield", "alpha" }) {
            if (!props.has_property(name) || props.type(name) != Properties::Type::Object)
                continue;
            ref<Texture> tex = props.get_texture<Texture>(name);
            if (tex->is_spatially_varying())
                Throw("%s: a texture for \"%s\" is not available in the vectorised variants yet (it is in "
                      "scalar_rgb and scalar_spectral); give a float", Plugin, name);
            double v = fluo_detail::host_value(tex->eval_1(dr::zeros<SurfaceInteraction3f>(), true));
            std::string_view n(name);
            (n == "radius" ? m_config.radius : n == "density" ? m_config.density
             : n == "quantum_yield" ? m_config.quantum_yield : m_config.alpha) = v;
            props.mark_queried(name);
        }
        m_setup.parse(props, m_config, [&](const char *name) {
            return props.has_property(name) && props.type(name) == Properties::Type::Object;
        });
        m_type = m_config.ggx ? MicrofacetType::GGX : MicrofacetType::Beckmann;
        m_flags = BSDFFlags::GlossyReflection | BSDFFlags::FrontSide;
        m_components.push_back(m_flags);
        rebuild();
        sync_members();
    }

    void traverse(TraversalCallback *cb) override {
        Base::traverse(cb);
        cb->put("quantum_yield", m_q, ParamFlags::Differentiable);
        cb->put("radius", m_radius, ParamFlags::NonDifferentiable);
        cb->put("density", m_density, ParamFlags::NonDifferentiable);
        cb->put("alpha", m_alpha, ParamFlags::NonDifferentiable);
        cb->put("width", m_width, ParamFlags::NonDifferentiable);
        cb->put("eta", m_setup.eta, ParamFlags::NonDifferentiable);
        cb->put("k", m_setup.k, ParamFlags::NonDifferentiable);
    }

    /// Rust validates the new values and bakes the tables again; a rejected update restores
    /// the previous ones, so the material keeps working. Q keeps its AD graph (the
    /// reradiation is linear in it).
    void parameters_changed(const std::vector<std::string> &keys) override {
        fluo::QdConfig previous = m_config;
        try {
            m_config.quantum_yield = fluo_detail::host_value(m_q);
            m_config.radius = m_radius;
            m_config.density = m_density;
            m_config.alpha = m_alpha;
            m_config.width = m_width;
            rebuild();
        } catch (...) {
            m_config = previous;
            rebuild();
            sync_members();
            throw;
        }
        Base::parameters_changed(keys);
    }

    std::pair<BSDFSample3f, Spectrum> sample(const BSDFContext &ctx, const SurfaceInteraction3f &si,
                                             Float /* sample1 */, const Point2f &sample2,
                                             Mask active) const override {
        return sample_with(ctx, si, sample2, active, cells_of(si, active));
    }

    Spectrum eval(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
                  Mask active) const override {
        return eval_pdf_with(ctx, si, wo, active, cells_of(si, active)).first;
    }

    Float pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
              Mask active) const override {
        Float cos_theta_i = Frame3f::cos_theta(si.wi), cos_theta_o = Frame3f::cos_theta(wo);
        Vector3f m = dr::normalize(wo + si.wi);
        active &= cos_theta_i > 0.f && cos_theta_o > 0.f && dr::dot(si.wi, m) > 0.f && dr::dot(wo, m) > 0.f;
        if (unlikely(!ctx.is_enabled(BSDFFlags::GlossyReflection) || dr::none_or<false>(active)))
            return 0.f;
        MicrofacetDistribution distr(m_type, m_alpha_f, m_alpha_f, true);
        return dr::select(active, distr.eval(m) * distr.smith_g1(si.wi, m) / (4.f * cos_theta_i), 0.f);
    }

    std::pair<Spectrum, Float> eval_pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si,
                                        const Vector3f &wo, Mask active) const override {
        return eval_pdf_with(ctx, si, wo, active, cells_of(si, active));
    }

    /// eval_pdf and sample sharing the wavelengths' table cells.
    std::tuple<Spectrum, Float, BSDFSample3f, Spectrum> eval_pdf_sample(const BSDFContext &ctx,
                                                                        const SurfaceInteraction3f &si,
                                                                        const Vector3f &wo, Float /* sample1 */,
                                                                        const Point2f &sample2,
                                                                        Mask active) const override {
        Cells cells = cells_of(si, active);
        auto [value, pdf] = eval_pdf_with(ctx, si, wo, active, cells);
        auto [bs, weight] = sample_with(ctx, si, sample2, active, cells);
        return { value, pdf, bs, weight };
    }

    // ------------------------------------------------ fluo_path's interface (fluo_jit.h)
    bool jit_fluorescent() const override { return fluo::qd_is_fluorescent(**m_model); }
    fluo::Range jit_emission_range() const override {
        return fluo::fluo_emission_range(fluo::qd_fluorescence(**m_model));
    }
    bool jit_lambertian() const override { return false; }

    /// No Lambertian operator: jit_reduced_nodes serves the reradiation.
    bool jit_reduced_matrices(const fluo::TransportBasis &, std::array<std::vector<double>, MaxTerms> &) const override {
        return false;
    }
    /// Rust's reduced matrices at the microfacet cosines (the scalar fluo_path's), per unit
    /// Q (w_0 = Q carries it), as at most MaxTerms terms s_t(cos θ)·B_t (a truncated SVD:
    /// within 1e-5 of the largest entry for every coating measured; a warning says so where
    /// it is not).
    size_t jit_reduced_nodes(const fluo::TransportBasis &transport, std::array<std::vector<double>, MaxTerms> &m,
                             std::vector<double> &nodes) const override {
        // fluo_path asks once per render; the reduction (17 operators) is kept per basis
        // until the model is rebuilt.
        std::string key = std::string(fluo::transport_label(transport)) + "/" + std::to_string(m_build);
        if (key != m_reduced_key) {
            m_reduced_m = m;
            m_reduced_n = reduce_nodes(transport, m_reduced_m, m_reduced_nodes);
            m_reduced_key = key;
        }
        m = m_reduced_m;
        nodes = m_reduced_nodes;
        return m_reduced_n;
    }

    size_t reduce_nodes(const fluo::TransportBasis &transport, std::array<std::vector<double>, MaxTerms> &m,
                        std::vector<double> &nodes) const {
        size_t kk = m[0].size(), n = fluo::reduced_microfacet_nodes();
        std::vector<double> basis(MaxTerms * kk);
        nodes.assign(n * MaxTerms, 0.0);
        auto reduced = fluo::reduced_new(fluo::qd_fluorescence(**m_model), transport);
        double error = fluo::reduced_microfacet_low_rank(*reduced, MaxTerms, rust::Slice<double>(basis.data(), basis.size()),
                                                         rust::Slice<double>(nodes.data(), nodes.size()));
        if (!(error >= 0.0) || !std::isfinite(error))
            Throw("%s: no microfacet reduced operator", Plugin);
        if (error > fluo::reduced_low_rank_tolerance())
            Log(Warn, "%s: the reduced reradiation of this coating is held by %zu terms to %.2g of its largest "
                      "entry in the vectorised variants (expected below %.2g): RGB renders may differ from "
                      "scalar_rgb by about that much", Plugin, MaxTerms, error, fluo::reduced_low_rank_tolerance());
        double inv_q = 1.0 / m_config.quantum_yield; // fluorescent: Q > 0
        for (size_t t = 0; t < MaxTerms; ++t)
            for (size_t i = 0; i < kk; ++i)
                m[t][i] = basis[t * kk + i] * inv_q;
        return n;
    }
    std::array<Float, MaxTerms> jit_reduced_weights() const override { return { m_q, Float(0.f), Float(0.f) }; }

    /// The microfacet lobe D G/(4 cos θi) and cos θ = ωi·h (as the Rust model's lobe).
    std::pair<Float, Float> jit_lobe(const SurfaceInteraction3f &si, const Vector3f &wo, Mask active) const override {
        Float cos_i = Frame3f::cos_theta(si.wi);
        Vector3f h = dr::normalize(wo + si.wi);
        MicrofacetDistribution distr(m_type, m_alpha_f, m_alpha_f, true);
        Float g = distr.smith_g1(si.wi, h) * distr.smith_g1(wo, h), c = dr::minimum(dr::dot(si.wi, h), 1.f);
        Float lobe = distr.eval(h) * g / (4.f * cos_i);
        active &= cos_i > 0.f && Frame3f::cos_theta(wo) > 0.f && g > 0.f && c > 0.f && dr::isfinite(lobe);
        return { dr::select(active, lobe, 0.f), dr::select(active, c, 0.f) };
    }

    /// Smooth-surface R_tot(θi, λ) (spectral), or per RGB channel.
    UnpolarizedSpectrum jit_elastic_albedo(const SurfaceInteraction3f &si, Mask active) const override {
        return fresnel_value(si, dr::maximum(Frame3f::cos_theta(si.wi), 0.f), active, cells_of(si, active));
    }

    Choice jit_choose(const SurfaceInteraction3f &si, const Wavelength &u1, const Wavelength &u2, double range_lo,
                      double range_hi, Mask active) const override {
        const Wavelength &lambda_o = si.wavelengths;
        if constexpr (!is_spectral_v<Spectrum>) {
            return this->elastic_only(lambda_o);
        } else {
            Float cos_i = Frame3f::cos_theta(si.wi);
            // The cells of λo serve the elastic weight and, where λo is below the range's top,
            // the excitation interval's upper end; its lower end is the same for every lane.
            Cells cells = cells_of(si, active); // fluorescent: coated
            // The elastic event's weight: the smooth surface's R_tot from Rust's table (any
            // weight positive where the elastic lobe is keeps the estimator unbiased; this one
            // spares the substrate's eta/k lookups).
            UnpolarizedSpectrum we;
            for (size_t w = 0; w < cells.size(); ++w)
                we[w] = dr::maximum(bilinear(m_r_tot, dr::maximum(cos_i, 0.f), cells[w], active), 0.f);
            double a_host = std::max(range_lo, (double) m_ex_lo), hi_host = std::min(range_hi, (double) m_ex_hi);
            Cell ca = host_cell(a_host), c_hi = host_cell(hi_host);
            Wavelength lambda_i = lambda_o;
            UnpolarizedSpectrum scale(0.f), rerad(0.f);
            WMask shifted(false);
            // The A_tot row nearest cos θi (as the Rust model's sampling).
            UInt32 row = UInt32(dr::round(dr::clip(cos_i, 0.f, 1.f) * (float) (m_rows - 1))) * m_grid.n;
            Float hi_r = (float) hi_host;
            for (size_t w = 0; w < dr::size_v<Wavelength>; ++w) {
                // The excitation interval [a, b] (λi ≤ λo), e(λo | a) and the row's mass there.
                Float lo = lambda_o[w], a = (float) a_host, b = dr::minimum(hi_r, lo);
                Mask ok = active && cos_i > 0.f && b > a && lo >= m_lmin && lo <= m_lmax;
                Float e = dr::select(ok, emission(lo), 0.f);
                ok &= e > 0.f;
                Mask below = lo < hi_r;
                Cell cb{ dr::select(below, cells[w].k, c_hi.k), dr::select(below, cells[w].f, c_hi.f),
                         dr::select(below, cells[w].x0, c_hi.x0), dr::select(below, cells[w].x1, c_hi.x1) };
                Float c_a = running(row, ca, ok), c_b = running(row, cb, ok);
                Float mass = dr::select(ok, dr::maximum(c_b - c_a, 0.f), 0.f);
                ok &= mass > 0.f;
                fluo_detail::ShiftChoice<Float> choice(we[w], dr::detach(m_q) * e * mass, u1[w], active);
                // λi ∝ the row on [a, b]: the last node whose running integral is ≤ the target,
                // then the cell's quadratic root (cancellation-free form).
                Float target = c_a + dr::clip(u2[w], 0.f, 1.f) * mass;
                UInt32 k = dr::binary_search<UInt32>(1, m_grid.n - 1, [&](const UInt32 &i) {
                               return dr::gather<Float>(m_cdf, row + i, ok) <= target;
                           }) - 1;
                k = dr::clip(k, ca.k, cb.k);
                Float x0 = dr::gather<Float>(m_grid.nodes, k, ok), x1 = dr::gather<Float>(m_grid.nodes, k + 1, ok);
                Float f0 = dr::gather<Float>(m_a_tot, row + k, ok), f1 = dr::gather<Float>(m_a_tot, row + k + 1, ok);
                Float h = x1 - x0;
                Float step = fluo_detail::linear_cell_inverse(f0, f1, h, target - dr::gather<Float>(m_cdf, row + k, ok));
                Float x = dr::clip(x0 + step, dr::maximum(a, x0), dr::minimum(b, x1));
                Float pdf = dr::select(ok, dr::lerp(f0, f1, dr::clip((x - x0) / h, 0.f, 1.f)) / mass, 0.f);
                scale[w] = choice.weight(pdf, u1[w]);
                shifted[w] = choice.shifted;
                lambda_i[w] = dr::select(choice.shifted, x, lo);
                rerad[w] = dr::select(choice.shifted, m_q * e, 0.f); // Q·e(λo | λi), nm⁻¹
            }
            return { lambda_i, scale, shifted, rerad };
        }
    }

    /// lobe(ωi, ωo)·A_tot(ωi·h, λi)·rerad towards both directions (si.wavelengths = λi).
    std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum> jit_reradiation(const SurfaceInteraction3f &si,
                                                                        const UnpolarizedSpectrum &rerad,
                                                                        const Vector3f &wo_a, const Vector3f &wo_b,
                                                                        Mask active) const override {
        UnpolarizedSpectrum out_a(0.f), out_b(0.f);
        if constexpr (is_spectral_v<Spectrum>) {
            auto [lobe_a, c_a] = jit_lobe(si, wo_a, active);
            auto [lobe_b, c_b] = jit_lobe(si, wo_b, active);
            for (size_t w = 0; w < dr::size_v<Wavelength>; ++w) {
                Mask on = active && rerad[w] != 0.f;
                Cell c = cell(si.wavelengths[w], on);
                out_a[w] = rerad[w] * lobe_a * bilinear(m_a_tot, c_a, c, on);
                out_b[w] = rerad[w] * lobe_b * bilinear(m_a_tot, c_b, c, on);
            }
        } else {
            (void) si, (void) rerad, (void) wo_a, (void) wo_b, (void) active;
        }
        return { out_a, out_b };
    }

    std::string to_string() const override {
        std::ostringstream oss;
        oss << "FluoQd[" << std::endl
            << "  model = " << std::string(fluo::qd_to_string(**m_model)) << "," << std::endl
            << "  eta = " << string::indent(m_setup.eta) << "," << std::endl
            << "  k = " << string::indent(m_setup.k) << "," << std::endl
            << "  variant = vectorised (tables per lane, " << m_rows << " x " << m_grid.n << ")" << std::endl
            << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(FluoQdJit)

private:
    /// λ in the table's cell k (λ_k = x0 ≤ λ ≤ λ_{k+1} = x1, clamped to the grid) at fraction f.
    using Cell = typename fluo_detail::JitGrid<Float>::Cell;
    /// The cells of si.wavelengths (spectral; unused in RGB).
    using Cells = std::array<Cell, dr::size_v<UnpolarizedSpectrum>>;

    /// The cell of λ (the grid's bucket index, else binary search).
    Cell cell(const Float &lambda, const Mask &active) const { return m_grid.cell(lambda, active); }
    /// The cell of a wavelength known on the host (the same for every lane).
    Cell host_cell(double lambda) const {
        auto [k, f] = m_grid.host_cell(lambda);
        return { UInt32((uint32_t) k), Float((float) f), Float((float) m_grid.host[k]), Float((float) m_grid.host[k + 1]) };
    }
    Cells cells_of(const SurfaceInteraction3f &si, const Mask &active) const {
        Cells c;
        if constexpr (is_spectral_v<Spectrum>) {
            if (m_coated)
                for (size_t w = 0; w < c.size(); ++w)
                    c[w] = cell(si.wavelengths[w], active);
        } else {
            (void) si, (void) active;
        }
        return c;
    }

    std::pair<BSDFSample3f, Spectrum> sample_with(const BSDFContext &ctx, const SurfaceInteraction3f &si,
                                                  const Point2f &sample2, Mask active, const Cells &cells) const {
        BSDFSample3f bs = dr::zeros<BSDFSample3f>();
        Float cos_theta_i = Frame3f::cos_theta(si.wi);
        active &= cos_theta_i > 0.f;
        if (unlikely(!ctx.is_enabled(BSDFFlags::GlossyReflection) || dr::none_or<false>(active)))
            return { bs, 0.f };
        MicrofacetDistribution distr(m_type, m_alpha_f, m_alpha_f, true);
        auto [m, pdf] = distr.sample(si.wi, sample2);
        bs.wo = reflect(si.wi, m);
        bs.eta = 1.f;
        bs.sampled_component = 0;
        bs.sampled_type = +BSDFFlags::GlossyReflection;
        active &= (pdf != 0.f) && Frame3f::cos_theta(bs.wo) > 0.f;
        bs.pdf = dr::select(active, pdf / (4.f * dr::dot(bs.wo, m)), 0.f);
        UnpolarizedSpectrum weight = distr.smith_g1(bs.wo, m) * fresnel_value(si, dr::dot(si.wi, m), active, cells);
        return { bs, depolarizer<Spectrum>(dr::select(active, weight, 0.f)) };
    }

    std::pair<Spectrum, Float> eval_pdf_with(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
                                             Mask active, const Cells &cells) const {
        Float cos_theta_i = Frame3f::cos_theta(si.wi), cos_theta_o = Frame3f::cos_theta(wo);
        Vector3f H = dr::normalize(wo + si.wi);
        active &= cos_theta_i > 0.f && cos_theta_o > 0.f && dr::dot(si.wi, H) > 0.f && dr::dot(wo, H) > 0.f;
        if (unlikely(!ctx.is_enabled(BSDFFlags::GlossyReflection) || dr::none_or<false>(active)))
            return { 0.f, 0.f };
        MicrofacetDistribution distr(m_type, m_alpha_f, m_alpha_f, true);
        Float D = distr.eval(H), smith_g1_wi = distr.smith_g1(si.wi, H);
        Float G = smith_g1_wi * distr.smith_g1(wo, H);
        UnpolarizedSpectrum value = fresnel_value(si, dr::dot(si.wi, H), active, cells) * (D * G / (4.f * cos_theta_i));
        Float pdf = D * smith_g1_wi / (4.f * cos_theta_i);
        return { depolarizer<Spectrum>(dr::select(active, value, 0.f)), dr::select(active, pdf, 0.f) };
    }
    /// A table's row (offset `row`) at the cell, linear in λ.
    Float along(const FloatStorage &t, const UInt32 &row, const Cell &c, const Mask &active) const {
        return dr::lerp(dr::gather<Float>(t, row + c.k, active), dr::gather<Float>(t, row + c.k + 1, active), c.f);
    }
    /// The running integral of row `row` (offset) of A_tot up to the cell's λ.
    Float running(const UInt32 &row, const Cell &c, const Mask &active) const {
        Float f0 = dr::gather<Float>(m_a_tot, row + c.k, active), f1 = dr::gather<Float>(m_a_tot, row + c.k + 1, active);
        Float half = .5f * c.f * (c.x1 - c.x0);
        return dr::gather<Float>(m_cdf, row + c.k, active) + half * (f0 + dr::lerp(f0, f1, c.f));
    }
    /// Rows j, j + 1 around cos θ and the fraction between them.
    std::pair<UInt32, Float> rows_at(const Float &cos_theta) const {
        Float x = dr::clip(cos_theta, 0.f, 1.f) * (float) (m_rows - 1);
        UInt32 j = dr::minimum(UInt32(dr::floor(x)), m_rows - 2);
        return { j, x - Float(j) };
    }
    /// A [rows][λ] table, bilinear in (cos θ, λ).
    Float bilinear(const FloatStorage &t, const Float &cos_theta, const Cell &c, const Mask &active) const {
        auto [j, fc] = rows_at(cos_theta);
        UInt32 r0 = j * m_grid.n;
        return dr::lerp(along(t, r0, c, active), along(t, r0 + m_grid.n, c, active), fc);
    }

    /// e(λo | λi) = L(λo)/I (λo > λi, within [λmin, λmax], checked by the caller): the
    /// logistic density exp(−|u|)/(s(1 + exp(−|u|))²), u = (λo − peak)/s, as band.rs.
    Float emission(const Float &lambda_o) const {
        Float e = dr::exp(-dr::abs((lambda_o - m_peak) * (1.f / m_scale)));
        return e / (m_scale * dr::square(1.f + e)) * m_inv_norm;
    }

    /// The substrate's Fresnel factor F (its eta/k textures, as roughconductor), and with a
    /// coating R_tot = R_spe + pass·F/(1 − F·R_spe) (eq. 23).
    UnpolarizedSpectrum fresnel_value(const SurfaceInteraction3f &si, const Float &cos_m, const Mask &active,
                                      const Cells &cells) const {
        if (m_tabulated) {
            // a uniform substrate under the coating: R_tot itself from Rust's table (the
            // scalar lobe's r_tot at the nodes), no substrate lookups and Fresnel per lane
            UnpolarizedSpectrum r_tot;
            if constexpr (is_spectral_v<Spectrum>) {
                for (size_t w = 0; w < dr::size_v<Wavelength>; ++w)
                    r_tot[w] = bilinear(m_r_tot, cos_m, cells[w], active);
            } else {
                auto [j, fc] = rows_at(cos_m);
                for (size_t ch = 0; ch < 3; ++ch) {
                    UInt32 i0 = j * 3 + (uint32_t) ch, i1 = i0 + 3;
                    r_tot[ch] = dr::lerp(dr::gather<Float>(m_rgb_r_tot, i0, active),
                                         dr::gather<Float>(m_rgb_r_tot, i1, active), fc);
                }
            }
            return r_tot;
        }
        dr::Complex<UnpolarizedSpectrum> eta_c(m_setup.eta->eval(si, active), m_setup.k->eval(si, active));
        UnpolarizedSpectrum F = fresnel_conductor(UnpolarizedSpectrum(cos_m), eta_c);
        if (!m_coated)
            return F;
        UnpolarizedSpectrum r_spe, pass;
        if constexpr (is_spectral_v<Spectrum>) {
            for (size_t w = 0; w < dr::size_v<Wavelength>; ++w) {
                r_spe[w] = bilinear(m_r_spe, cos_m, cells[w], active);
                pass[w] = bilinear(m_pass, cos_m, cells[w], active);
            }
        } else {
            auto [j, fc] = rows_at(cos_m);
            for (size_t ch = 0; ch < 3; ++ch) {
                UInt32 i0 = j * 3 + (uint32_t) ch, i1 = i0 + 3;
                r_spe[ch] = dr::lerp(dr::gather<Float>(m_rgb_r_spe, i0, active), dr::gather<Float>(m_rgb_r_spe, i1, active), fc);
                pass[ch] = dr::lerp(dr::gather<Float>(m_rgb_pass, i0, active), dr::gather<Float>(m_rgb_pass, i1, active), fc);
            }
        }
        return r_spe + pass * F / dr::maximum(1.f - F * r_spe, 1e-12f);
    }

    static FloatStorage storage(const rust::Vec<double> &v) {
        std::vector<float> f(v.begin(), v.end());
        return dr::load<FloatStorage>(f.data(), f.size());
    }

    /// Validate the configuration in Rust, build the model and bake the tables.
    void rebuild() {
        fluo_detail::QdSamples eta, k, qd_eta, qd_k; // qd_eta, qd_k empty: built-in CdSe
        m_setup.sample_all(m_config, eta, k, qd_eta, qd_k);
        rust::Box<fluo::QdModel> model = fluo_detail::rust_call(Plugin, [&] {
            return fluo::qd_new(m_config, eta.view(), k.view(), qd_eta.view(), qd_k.view());
        });
        if (fluo::qd_is_fluorescent(*model) && !m_setup.uniform_substrate())
            Throw("%s: a spatially varying substrate (textured \"eta\"/\"k\") cannot be combined "
                  "with a fluorescent coating: the coating's absorption tables are baked for one "
                  "substrate (the elastic part alone is evaluated per hit); give constant "
                  "\"eta\"/\"k\", or \"density\" = 0 or \"quantum_yield\" = 0",
                  Plugin);
        const float *rgb = Setup::RgbWavelengths;
        std::array<double, 3> extra = { rgb[0], rgb[1], rgb[2] };
        fluo::QdJitTables t =
            fluo::qd_jit_tables(*model, JitCosNodes, rust::Slice<const double>(extra.data(), extra.size()));
        if (t.lambda.size() < 2 || t.rows < 2)
            Throw("%s: the coating's tables have %zu wavelengths and %zu rows (at least 2 each expected)", Plugin,
                  t.lambda.size(), t.rows);
        m_model = std::move(model);
        m_grid.set(std::vector<double>(t.lambda.begin(), t.lambda.end()));
        m_rows = (uint32_t) t.rows;
        m_a_tot = storage(t.a_tot);
        m_cdf = storage(t.cdf);
        m_r_spe = storage(t.r_spe);
        m_pass = storage(t.pass);
        m_r_tot = storage(t.r_tot);
        m_rgb_r_spe = storage(t.extra_r_spe);
        m_rgb_pass = storage(t.extra_pass);
        m_peak = (float) t.emission_peak_nm;
        m_scale = (float) t.emission_scale_nm;
        m_inv_norm = t.emission_norm > 0.0 ? (float) (1.0 / t.emission_norm) : 0.f;
        m_lmin = (float) t.lambda_min;
        m_lmax = (float) t.lambda_max;
        m_ex_lo = (float) t.excitation_lo;
        m_ex_hi = (float) t.excitation_hi;
        // Mitsuba's own clamp of a zero roughness.
        m_alpha_f = dr::maximum((ScalarFloat) m_config.alpha, (ScalarFloat) 1e-4f);
        m_coated = m_config.density > 0.0;
        m_tabulated = m_coated && m_setup.uniform_substrate();
        if (m_tabulated && !is_spectral_v<Spectrum>) {
            // RGB: R_tot per channel at the cosine nodes from the channels' R_spe and pass and
            // the substrate's (uniform) eta/k, as fresnel_value computes it per lane
            auto eta = m_setup.eta->eval(dr::zeros<SurfaceInteraction3f>(), true);
            auto k = m_setup.k->eval(dr::zeros<SurfaceInteraction3f>(), true);
            std::vector<double> r_tot(t.extra_r_spe.size());
            for (size_t j = 0; j < t.rows; ++j)
                for (size_t ch = 0; ch < 3; ++ch) {
                    double cos_m = (double) j / (double) (t.rows - 1);
                    dr::Complex<double> eta_c(fluo_detail::host_value(eta[ch]), fluo_detail::host_value(k[ch]));
                    double f = fresnel_conductor(cos_m, eta_c), r = t.extra_r_spe[j * 3 + ch],
                           pass = t.extra_pass[j * 3 + ch];
                    r_tot[j * 3 + ch] = r + pass * f / std::max(1.0 - f * r, 1e-12);
                }
            std::vector<float> f(r_tot.begin(), r_tot.end());
            m_rgb_r_tot = dr::load<FloatStorage>(f.data(), f.size());
        }
        ++m_build;
    }

    /// The traversed members from the configuration (at load, and after a rejected update;
    /// an accepted one keeps Q's AD graph).
    void sync_members() {
        m_q = (ScalarFloat) m_config.quantum_yield;
        m_radius = (ScalarFloat) m_config.radius;
        m_density = (ScalarFloat) m_config.density;
        m_alpha = (ScalarFloat) m_config.alpha;
        m_width = (ScalarFloat) m_config.width;
    }

    fluo::QdConfig m_config = fluo::qd_default_config(); ///< the defaults live in Rust (QdParams)
    std::optional<rust::Box<fluo::QdModel>> m_model;
    Setup m_setup;
    MicrofacetType m_type = MicrofacetType::Beckmann;
    ScalarFloat m_alpha_f = 0.1f;
    bool m_coated = false;
    /// coated over a uniform substrate: the elastic lobe's R_tot from the tables (fresnel_value)
    bool m_tabulated = false;
    // the tables ([rows][λ] row major) and their grid
    FloatStorage m_a_tot, m_cdf, m_r_spe, m_pass, m_r_tot, m_rgb_r_spe, m_rgb_pass, m_rgb_r_tot;
    uint32_t m_rows = 2; ///< the tables' rows (cosine nodes); a row is m_grid.n long
    uint64_t m_build = 0; ///< counts rebuilds: keys the reduction below
    // the reduced operator of the last basis fluo_path asked for (jit_reduced_nodes)
    mutable std::string m_reduced_key;
    mutable std::array<std::vector<double>, MaxTerms> m_reduced_m;
    mutable std::vector<double> m_reduced_nodes;
    mutable size_t m_reduced_n = 0;
    fluo_detail::JitGrid<Float> m_grid; ///< the λ grid and its bucket index
    float m_peak = 0.f, m_scale = 1.f, m_inv_norm = 0.f, m_lmin = 0.f, m_lmax = 0.f;
    float m_ex_lo = 0.f, m_ex_hi = 0.f;
    Float m_q = 0.f; ///< Q (differentiable)
    ScalarFloat m_radius = 0.f, m_density = 0.f, m_alpha = 0.f, m_width = 0.f;

    MI_TRAVERSE_CB(Base, m_grid.nodes, m_a_tot, m_cdf, m_r_spe, m_pass, m_r_tot, m_rgb_r_spe, m_rgb_pass, m_rgb_r_tot,
                   m_grid.buckets, m_q)
};

static const bool fluo_qd_jit_registered =
    (fluo_detail::register_jit_plugin<FluoQdJit>("fluo_qd", ObjectType::BSDF), true);

NAMESPACE_END(mitsuba)
