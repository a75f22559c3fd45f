// fluo_jung in the vectorised variants (llvm_ad_rgb, llvm_ad_spectral). The plugin's
// documentation, and the reference implementation the tests hold this one against, are in
// fluo_jung.cpp; what differs here is said there under "Vectorised variants".
//
// Rust validates the parameters and bakes, at load and in parameters_changed(): the dye's
// absorption on a grid (the table that samples excitation wavelengths), the RGB parts and,
// through fluo_path, the reduced matrices. Per lane the shim evaluates Jung's closed forms
// (fluo_jit.h) with Dr.Jit types, so gradients reach c, Q, λe, s and the reflectance.
#include <mitsuba/core/distr_1d.h>
#include <mitsuba/core/fresolver.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/texture.h>

#include <optional>
#include <vector>

#include "fluo_common.h"
#include "fluo_jit.h"
#include "fluo_lambertian.h"

NAMESPACE_BEGIN(mitsuba)

template <typename Float, typename Spectrum>
class FluoJungJit final : public BSDF<Float, Spectrum>, public fluo_detail::JitBispectral<Float, Spectrum> {
public:
    MI_IMPORT_BASE(BSDF, m_flags, m_components)
    MI_IMPORT_TYPES(Texture)
    using WMask = dr::mask_t<UnpolarizedSpectrum>;
    using Dye = fluo_detail::JungDye<UnpolarizedSpectrum>;
    using fluo_detail::JitBispectral<Float, Spectrum>::MaxTerms;

    static constexpr const char *Plugin = "fluo_jung";
    /// Nodes of the absorption table that samples excitation wavelengths (the values
    /// weighting a sample are the closed form's: the table only shapes the variance).
    static constexpr size_t AbsorptionNodes = 512;

    FluoJungJit(const Properties &props) : Base(props) {
        using namespace fluo_detail;
        for (const char *name : { "emission_peak", "stokes_shift", "concentration", "quantum_yield" })
            if (props.has_property(name) && props.type(name) == Properties::Type::Object)
                Throw("%s: a texture for \"%s\" is not available in the vectorised variants yet (it is in "
                      "scalar_rgb and scalar_spectral); give a float", Plugin, name);
        m_config.emission_peak = get_float(Plugin, props, "emission_peak", m_config.emission_peak);
        m_config.stokes_shift = get_float(Plugin, props, "stokes_shift", m_config.stokes_shift);
        m_config.concentration = get_float(Plugin, props, "concentration", m_config.concentration);
        m_config.quantum_yield = get_float(Plugin, props, "quantum_yield", m_config.quantum_yield);
        m_config.has_coefficients = props.has_property("coefficients");
        if (props.has_property("color")) {
            init_color(props);
        } else if (m_config.has_coefficients) {
            if (props.has_property("reflectance"))
                Throw("%s: specify either \"reflectance\" or \"coefficients\", not both", Plugin);
            auto c = parse_list<3>(Plugin, "coefficients", std::string(props.get<std::string_view>("coefficients")));
            m_config.c0 = c[0];
            m_config.c1 = c[1];
            m_config.c2 = c[2];
        } else {
            m_reflectance = props.get_texture<Texture>("reflectance", .5f);
            check_texture_range(Plugin, "reflectance", m_reflectance.get(), 0.0, 1.0);
        }
        m_peak = (ScalarFloat) m_config.emission_peak;
        m_shift = (ScalarFloat) m_config.stokes_shift;
        m_conc = (ScalarFloat) m_config.concentration;
        m_yield = (ScalarFloat) m_config.quantum_yield;
        m_flags = BSDFFlags::DiffuseReflection | BSDFFlags::FrontSide;
        m_components.push_back(m_flags);
        rebuild();
    }

    void traverse(TraversalCallback *cb) override {
        Base::traverse(cb);
        if (m_color_mode)
            return; // everything derives from the colour and the cube
        if (m_reflectance)
            cb->put("reflectance", m_reflectance, ParamFlags::Differentiable);
        cb->put("emission_peak", m_peak, ParamFlags::Differentiable);
        cb->put("stokes_shift", m_shift, ParamFlags::Differentiable);
        cb->put("concentration", m_conc, ParamFlags::Differentiable);
        cb->put("quantum_yield", m_yield, ParamFlags::Differentiable);
    }

    void parameters_changed(const std::vector<std::string> &keys) override {
        // The JIT values keep their AD graph; Rust sees their detached values and
        // re-bakes the tables (a rejected update restores the previous values).
        fluo::JungConfig previous = m_config;
        Float prev[4] = { m_peak, m_shift, m_conc, m_yield };
        try {
            m_config.emission_peak = fluo_detail::host_value(m_peak);
            m_config.stokes_shift = fluo_detail::host_value(m_shift);
            m_config.concentration = fluo_detail::host_value(m_conc);
            m_config.quantum_yield = fluo_detail::host_value(m_yield);
            rebuild();
        } catch (...) {
            m_config = previous;
            m_peak = prev[0];
            m_shift = prev[1];
            m_conc = prev[2];
            m_yield = prev[3];
            rebuild();
            throw;
        }
        Base::parameters_changed(keys);
    }

    std::pair<BSDFSample3f, Spectrum> sample(const BSDFContext &ctx, const SurfaceInteraction3f &si,
                                             Float /* sample1 */, const Point2f &sample2,
                                             Mask active) const override {
        return Lambertian<Float, Spectrum>::sample(ctx, si, sample2, active, [&] { return albedo(si, active); });
    }

    Spectrum eval(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
                  Mask active) const override {
        return Lambertian<Float, Spectrum>::eval(ctx, si, wo, active, [&] { return albedo(si, active); });
    }

    Float pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
              Mask active) const override {
        return Lambertian<Float, Spectrum>::pdf(ctx, si, wo, active);
    }

    std::pair<Spectrum, Float> eval_pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si,
                                        const Vector3f &wo, Mask active) const override {
        return Lambertian<Float, Spectrum>::eval_pdf(ctx, si, wo, active, [&] { return albedo(si, active); });
    }

    Spectrum eval_diffuse_reflectance(const SurfaceInteraction3f &si, Mask active) const override {
        return depolarizer<Spectrum>(albedo(si, active));
    }

    // ------------------------------------------------ fluo_path's interface (fluo_jit.h)
    bool jit_fluorescent() const override { return fluo::jung_is_fluorescent(**m_model); }
    fluo::Range jit_emission_range() const override {
        return fluo::fluo_emission_range(fluo::jung_fluorescence(**m_model));
    }
    /// M = M_r − c·M_ra + c·Q·M_fl (fluo::jung_reduced_parts): exact for every c and Q.
    bool jit_reduced_matrices(const fluo::TransportBasis &transport,
                              std::array<std::vector<double>, MaxTerms> &m) const override {
        auto slice = [](std::vector<double> &v) { return rust::Slice<double>(v.data(), v.size()); };
        return fluo::jung_reduced_parts(**m_model, transport, slice(m[0]), slice(m[1]),
                                        slice(m[2]));
    }
    std::array<Float, MaxTerms> jit_reduced_weights() const override {
        return { Float(1.f), -m_conc, m_conc * m_yield };
    }

    UnpolarizedSpectrum jit_elastic_albedo(const SurfaceInteraction3f &si, Mask active) const override {
        if constexpr (is_rgb_v<Spectrum>) {
            if (m_reflectance)
                return m_reflectance->eval(si, active) * dr::clip(1.f - m_conc * m_rgb_absorbed_scale, 0.f, 1.f);
            return dr::clip(m_rgb_reflectance - m_conc * m_rgb_reflectance_absorbed, 0.f, 1.f);
        } else {
            return reflectance(si, active) * (1.f - m_conc * Dye(m_peak, m_shift).absorption(si.wavelengths));
        }
    }

    std::tuple<Wavelength, UnpolarizedSpectrum, WMask> jit_choose(const SurfaceInteraction3f &si,
                                                                 const Wavelength &u1, const Wavelength &u2,
                                                                 double range_lo, double range_hi,
                                                                 Mask active) const override {
        const Wavelength &lambda_o = si.wavelengths;
        if constexpr (!is_spectral_v<Spectrum>) {
            return { lambda_o, UnpolarizedSpectrum(1.f), WMask(false) };
        } else {
            // Probabilities are detached: gradients flow through the values only.
            Dye dye(dr::detach(m_peak), dr::detach(m_shift));
            UnpolarizedSpectrum we = dr::maximum(dr::detach(jit_elastic_albedo(si, active)), 0.f);
            double lo = std::max(range_lo, m_support_lo), hi = std::min(range_hi, m_support_hi);
            UnpolarizedSpectrum wf = 0.f, cdf_lo = 0.f, mass = 0.f;
            if (lo < hi && jit_fluorescent()) {
                cdf_lo = m_absorption.eval_cdf(Wavelength((ScalarFloat) lo), active);
                mass = m_absorption.eval_cdf(Wavelength((ScalarFloat) hi), active) - cdf_lo;
                wf = dr::detach(m_conc * m_yield) * dye.emission(lambda_o) * mass;
            }
            UnpolarizedSpectrum total = we + wf;
            WMask valid = WMask(active) && total > 0.f && dr::isfinite(total);
            UnpolarizedSpectrum pe = dr::select(valid, we / total, 1.f);
            WMask shifted = valid && u1 >= pe && wf > 0.f;
            // λi from the table restricted to [lo, hi]: the unnormalised CDF at cdf_lo + u2·mass.
            Wavelength lambda_i = m_absorption.sample((cdf_lo + u2 * mass) * m_absorption.normalization(), shifted);
            UnpolarizedSpectrum pdf_i = m_absorption.eval_pdf(lambda_i, shifted) / mass;
            UnpolarizedSpectrum scale =
                dr::select(shifted, dr::rcp((1.f - pe) * pdf_i), dr::rcp(pe));
            shifted &= pdf_i > 0.f;
            scale = dr::select(valid && dr::isfinite(scale) && (shifted || u1 < pe), scale, 0.f);
            return { dr::select(shifted, lambda_i, lambda_o), scale, shifted };
        }
    }

    UnpolarizedSpectrum jit_reradiation(const SurfaceInteraction3f &si, const Vector3f &wo,
                                        const Wavelength &lambda_o, Mask active) const override {
        if constexpr (!is_spectral_v<Spectrum>) {
            return 0.f;
        } else {
            active &= Frame3f::cos_theta(si.wi) > 0.f && Frame3f::cos_theta(wo) > 0.f;
            Dye dye(m_peak, m_shift);
            UnpolarizedSpectrum v = m_conc * m_yield * dye.absorption(si.wavelengths) * dye.emission(lambda_o) *
                                    dr::InvPi<Float> * Frame3f::cos_theta(wo);
            return dr::select(WMask(active) && si.wavelengths < lambda_o, v, 0.f);
        }
    }

    std::string to_string() const override {
        std::ostringstream oss;
        oss << "FluoJung[" << std::endl
            << "  model = " << std::string(fluo::jung_to_string(**m_model)) << "," << std::endl;
        if (m_reflectance)
            oss << "  reflectance = " << string::indent(m_reflectance) << "," << std::endl;
        if (m_color_mode)
            oss << "  color = " << m_color_text << "," << std::endl;
        oss << "  variant = vectorised (closed forms per lane)" << std::endl << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(FluoJungJit)

private:
    /// Validate in Rust and bake what the lanes read.
    void rebuild() {
        using namespace fluo_detail;
        m_model = rust_call(Plugin, [&] { return fluo::jung_new(m_config); });
        double peak = m_config.emission_peak, shift = m_config.stokes_shift;
        m_unit = rust_call(Plugin, [&] {
            return fluo::jung_shapes_new(rust::Slice<const double>(&peak, 1), rust::Slice<const double>(&shift, 1));
        });
        const fluo::JungModel &unit = fluo::jung_shapes_model(**m_unit, 0);
        fluo::Range ex = fluo::fluo_excitation_range(fluo::jung_fluorescence(unit));
        m_support_lo = ex.lo;
        m_support_hi = ex.hi;
        std::vector<float> lambda(AbsorptionNodes), a(AbsorptionNodes);
        for (size_t i = 0; i < AbsorptionNodes; ++i)
            lambda[i] = (float) (ex.lo + (ex.hi - ex.lo) * (double) i / (double) (AbsorptionNodes - 1));
        fluo::jung_absorption(unit, rust::Slice<const float>(lambda.data(), lambda.size()),
                              rust::Slice<float>(a.data(), a.size()));
        m_absorption = ContinuousDistribution<Wavelength>(
            ScalarVector2f((ScalarFloat) ex.lo, (ScalarFloat) ex.hi), a.data(), AbsorptionNodes);
        if constexpr (is_rgb_v<Spectrum>) {
            auto color = [](const fluo::Rgb &c) {
                return Color3f((ScalarFloat) c.r, (ScalarFloat) c.g, (ScalarFloat) c.b);
            };
            fluo::JungRgbParts p = fluo::jung_rgb_parts(unit, **m_model);
            m_rgb_reflectance = color(p.reflectance);
            m_rgb_reflectance_absorbed = color(p.reflectance_absorbed);
            m_rgb_absorbed_scale = color(p.absorbed_scale);
            m_rgb_fluorescence = color(p.fluorescence);
        }
    }

    /// r(λ): the reflectance texture, or the sigmoid of the coefficients.
    UnpolarizedSpectrum reflectance(const SurfaceInteraction3f &si, Mask active) const {
        if (m_reflectance)
            return m_reflectance->eval(si, active);
        if constexpr (is_spectral_v<Spectrum>)
            return fluo_detail::sigmoid_polynomial(si.wavelengths, m_config.c0, m_config.c1, m_config.c2);
        else
            return m_rgb_reflectance;
    }

    /// The albedo served to Mitsuba: the elastic part in spectral variants; in RGB ones the
    /// elastic part plus c·Q times the unit reradiation under equal-energy light, bounded
    /// per channel (fluo::colour::bounded_rgb_albedo, the scalar variants' rule: negative
    /// channels of each part clipped, the reradiation scaled by the largest k ≤ 1 keeping
    /// every channel ≤ 1).
    UnpolarizedSpectrum albedo(const SurfaceInteraction3f &si, Mask active) const {
        if constexpr (is_rgb_v<Spectrum>) {
            Color3f e = dr::clip(jit_elastic_albedo(si, active), 0.f, 1.f);
            Color3f f = dr::maximum(m_conc * m_yield * m_rgb_fluorescence, 0.f);
            Float k = 1.f;
            for (size_t c = 0; c < 3; ++c)
                k = dr::select(f[c] > 0.f, dr::minimum(k, (1.f - e[c]) / f[c]), k);
            k = dr::maximum(k, 0.f);
            return dr::minimum(e + k * f, 1.f);
        } else {
            return jit_elastic_albedo(si, active);
        }
    }

    /// `color` (a constant <rgb>): the cube's dye and sigmoid, as in the scalar variants.
    void init_color(const Properties &props) {
        using namespace fluo_detail;
        for (const char *other : { "reflectance", "coefficients", "emission_peak", "stokes_shift",
                                   "concentration", "quantum_yield" })
            if (props.has_property(other))
                Throw("%s: \"color\" sets the reflectance and fluorescence through the cube; "
                      "do not also specify \"%s\"", Plugin, other);
        if (props.type("color") != Properties::Type::Color)
            Throw("%s: a \"color\" texture is not available in the vectorised variants yet (it is in "
                  "scalar_rgb and scalar_spectral); give an <rgb> value", Plugin);
        m_color_mode = true;
        std::string space(props.get<std::string_view>("color_space", "acescg"));
        std::string cube_file(props.get<std::string_view>("cube", ""));
        if (!cube_file.empty())
            cube_file = mitsuba::file_resolver()->resolve(cube_file).string();
        std::string lookup(props.get<std::string_view>("lookup", "nearest"));
        bool use_fluorescence = props.get<bool>("fluorescence", true);
        auto cube = rust_call(Plugin, [&] { return fluo::upsample_cube_load(space, cube_file); });
        ScalarColor3f c = props.get<ScalarColor3f>("color");
        std::array<double, 3> rgb = { (double) c[0], (double) c[1], (double) c[2] };
        m_color_text = tfm::format("(%g, %g, %g) %s", rgb[0], rgb[1], rgb[2], space);
        m_config = rust_call(Plugin, [&] {
            return fluo::upsample_lookup(*cube, rust::Slice<const double>(rgb.data(), 3), lookup, use_fluorescence);
        });
    }

    fluo::JungConfig m_config = fluo::jung_default_config(); ///< the defaults live in Rust
    std::optional<rust::Box<fluo::JungModel>> m_model;      ///< validated at every rebuild
    std::optional<rust::Box<fluo::JungShapes>> m_unit;      ///< the dye at c = Q = 1
    ref<Texture> m_reflectance;                              ///< null: sigmoid coefficients
    Float m_peak, m_shift, m_conc, m_yield;                  ///< λe, s, c, Q (differentiable)
    double m_support_lo = 0.0, m_support_hi = 0.0;           ///< absorption support, nm
    ContinuousDistribution<Wavelength> m_absorption;        ///< samples λi ∝ a (unit peak)
    Color3f m_rgb_reflectance = 0.f, m_rgb_reflectance_absorbed = 0.f, m_rgb_absorbed_scale = 0.f,
            m_rgb_fluorescence = 0.f; ///< RGB variant: fluo::JungRgbParts of the unit dye
    bool m_color_mode = false;
    std::string m_color_text;

    MI_TRAVERSE_CB(Base, m_reflectance, m_peak, m_shift, m_conc, m_yield, m_absorption, m_rgb_reflectance,
                   m_rgb_reflectance_absorbed, m_rgb_absorbed_scale, m_rgb_fluorescence)
};

static const bool fluo_jung_jit_registered =
    (fluo_detail::register_jit_plugin<FluoJungJit>("fluo_jung", ObjectType::BSDF), true);

NAMESPACE_END(mitsuba)
