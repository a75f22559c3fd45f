// The BSDF shared by the measured-material plugins fluo_matrix and fluo_gmm
// (plugins/fluo_matrix.cpp, plugins/fluo_gmm.cpp document them).
//
// Both are diffuse in direction: the elastic part is Lambertian with the measured
// diagonal rho(lambda) as albedo, served through Mitsuba's BSDF interface; the
// reradiation P(lambda_i, lambda_o)/pi is served through fluo's bispectral interface
// (fluo_bispectral.h) to fluo_path. The two plugins differ only in the Rust
// constructor that reads their file.
#pragma once

#include <mitsuba/core/fresolver.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/core/warp.h>
#include <mitsuba/render/bsdf.h>

#include <optional>

#include "fluo_bispectral.h"
#include "fluo_common.h"
#include "fluo_lambertian.h"

NAMESPACE_BEGIN(mitsuba)

template <typename Float, typename Spectrum>
class FluoMeasured : public BSDF<Float, Spectrum>, public BispectralBSDF<Float, Spectrum> {
public:
    MI_IMPORT_BASE(BSDF, m_flags, m_components)
    MI_IMPORT_TYPES()

    using Factory = rust::Box<fluo::MeasuredModel> (*)(rust::Str);

    FluoMeasured(const Properties &props, const char *plugin, Factory factory)
        : Base(props), m_plugin(plugin) {
        if (!props.has_property("filename"))
            Throw("%s: parameter \"filename\" is required", plugin);
        std::string name(props.get<std::string_view>("filename"));
        fs::path path = file_resolver()->resolve(name);
        if (!fs::exists(path))
            Throw("%s: invalid parameter \"filename\" = \"%s\": file not found", plugin, name);
        m_filename = path.string();
        m_model = fluo_detail::rust_call(plugin, [&] { return factory(rust::Str(m_filename)); });
        m_flags = BSDFFlags::DiffuseReflection | BSDFFlags::FrontSide;
        m_components.push_back(m_flags);
        if constexpr (is_rgb_v<Spectrum>) {
            fluo::Rgb c = fluo::measured_rgb_albedo(**m_model);
            m_rgb_albedo = Color3f((ScalarFloat) c.r, (ScalarFloat) c.g, (ScalarFloat) c.b);
            fluo::Rgb e = fluo::measured_rgb_elastic(**m_model);
            m_rgb_elastic = dr::clip(Color3f((ScalarFloat) e.r, (ScalarFloat) e.g, (ScalarFloat) e.b), 0.f, 1.f);
        }
    }

    // traverse: nothing to expose (the file is the parameter); parameters_changed: none.

    std::pair<BSDFSample3f, Spectrum> sample(const BSDFContext &ctx, const SurfaceInteraction3f &si,
                                             Float /* sample1 */, const Point2f &sample2,
                                             Mask active) const override {
        this->warn_if_unmanaged(m_plugin);
        return Lambertian<Float, Spectrum>::sample(ctx, si, sample2, active, [&] { return albedo(si); });
    }

    Spectrum eval(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
                  Mask active) const override {
        return Lambertian<Float, Spectrum>::eval(ctx, si, wo, active, [&] { return albedo(si); });
    }

    Float pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
              Mask active) const override {
        return Lambertian<Float, Spectrum>::pdf(ctx, si, wo, active);
    }

    std::pair<Spectrum, Float> eval_pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si,
                                        const Vector3f &wo, Mask active) const override {
        return Lambertian<Float, Spectrum>::eval_pdf(ctx, si, wo, active, [&] { return albedo(si); });
    }

    Spectrum eval_diffuse_reflectance(const SurfaceInteraction3f &si, Mask /* active */) const override {
        return depolarizer<Spectrum>(albedo(si));
    }

    const fluo::Fluorescence *fluorescence() const override {
        return fluo::measured_is_fluorescent(**m_model) ? &fluo::measured_fluorescence(**m_model)
                                                        : nullptr;
    }

    /// The diagonal alone (in RGB its sRGB, without the equal-energy reradiation).
    UnpolarizedSpectrum elastic_albedo(const SurfaceInteraction3f &si) const override {
        if constexpr (is_rgb_v<Spectrum>)
            return m_rgb_elastic;
        else
            return albedo(si);
    }

    UnpolarizedSpectrum eval_elastic(const SurfaceInteraction3f &si, const Vector3f &wo) const override {
        Float cos_i = Frame3f::cos_theta(si.wi), cos_o = Frame3f::cos_theta(wo);
        if (!(cos_i > 0.f && cos_o > 0.f))
            return 0.f;
        return elastic_albedo(si) * dr::InvPi<Float> * cos_o;
    }

    std::string to_string() const override {
        std::ostringstream oss;
        oss << this->class_name() << "[" << std::endl
            << "  filename = \"" << m_filename << "\"," << std::endl
            << "  model = " << std::string(fluo::measured_to_string(**m_model)) << std::endl
            << "]";
        return oss.str();
    }

private:
    /// Spectral: the diagonal at the hero wavelengths. RGB: the albedo under
    /// equal-energy light (diagonal plus reradiation), in Mitsuba's sRGB convention.
    UnpolarizedSpectrum albedo(const SurfaceInteraction3f &si) const {
        if constexpr (is_rgb_v<Spectrum>) {
            (void) si;
            return m_rgb_albedo;
        } else {
            std::array<float, 4> lambda = fluo_detail::wavelengths_of(si.wavelengths), out{};
            fluo::measured_elastic_albedo(**m_model, fluo_detail::slice(lambda),
                                          fluo_detail::slice_mut(out));
            return UnpolarizedSpectrum(out[0], out[1], out[2], out[3]);
        }
    }

    const char *m_plugin;
    std::string m_filename;
    std::optional<rust::Box<fluo::MeasuredModel>> m_model;
    Color3f m_rgb_albedo = 0.f, m_rgb_elastic = 0.f;
};

NAMESPACE_END(mitsuba)
