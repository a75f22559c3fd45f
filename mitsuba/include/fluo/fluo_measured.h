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
#include <string>
#include <vector>

#include "fluo_bispectral.h"
#include "fluo_common.h"
#include "fluo_lambertian.h"
#include "fluo_measured_files.h"

NAMESPACE_BEGIN(mitsuba)

template <typename Float, typename Spectrum>
class FluoMeasured : public BSDF<Float, Spectrum>, public BispectralBSDF<Float, Spectrum> {
public:
    MI_IMPORT_BASE(BSDF, m_flags, m_components)
    MI_IMPORT_TYPES(Texture)

    using Factory = typename fluo_detail::MeasuredFiles<Float, Spectrum>::Factory;

    FluoMeasured(const Properties &props, const char *plugin, Factory factory)
        : Base(props), m_plugin(plugin) {
        fluo_detail::MeasuredFiles<Float, Spectrum> files(props, plugin, factory);
        m_keys = std::move(files.keys);
        m_filenames = std::move(files.paths);
        m_models = std::move(files.models);
        m_index = files.index;
        m_flags = BSDFFlags::DiffuseReflection | BSDFFlags::FrontSide;
        m_components.push_back(m_flags);
        for (const auto &m : m_models) {
            if (fluo::measured_is_fluorescent(*m) &&
                (m_representative < 0 || fluo::measured_emission_max(*m) >
                                             fluo::measured_emission_max(*m_models[(size_t) m_representative])))
                m_representative = (int) (&m - m_models.data());
            if constexpr (is_rgb_v<Spectrum>) {
                fluo::Rgb c = fluo::measured_rgb_albedo(*m);
                m_rgb_albedo.push_back(Color3f((ScalarFloat) c.r, (ScalarFloat) c.g, (ScalarFloat) c.b));
                fluo::Rgb e = fluo::measured_rgb_elastic(*m);
                m_rgb_elastic.push_back(
                    dr::clip(Color3f((ScalarFloat) e.r, (ScalarFloat) e.g, (ScalarFloat) e.b), 0.f, 1.f));
            }
        }
    }

    void traverse(TraversalCallback *cb) override {
        if (m_index)
            cb->put("index", m_index, ParamFlags::NonDifferentiable);
    }

    void parameters_changed(const std::vector<std::string> & /* keys */) override {
        if (m_index)
            fluo_detail::MeasuredFiles<Float, Spectrum>::check_index(m_plugin, m_index.get(),
                                                                     m_models.size()); // validated again
    }

    FLUO_LAMBERTIAN_BSDF_METHODS(albedo(si), this->warn_if_unmanaged(m_plugin))

    /// With an index texture: the fluorescent material with the longest emission
    /// (a representative for scene scans).
    const fluo::Fluorescence *fluorescence() const override {
        return m_representative >= 0 ? &fluo::measured_fluorescence(*m_models[(size_t) m_representative]) : nullptr;
    }

    const fluo::Fluorescence *fluorescence_at(const SurfaceInteraction3f &si) const override {
        if (!m_index)
            return fluorescence();
        const fluo::MeasuredModel &m = *m_models[material(si)];
        return fluo::measured_is_fluorescent(m) ? &fluo::measured_fluorescence(m) : nullptr;
    }

    bool fluorescence_varies() const override { return (bool) m_index; }

    size_t fluorescence_local(const SurfaceInteraction3f &si,
                              typename BispectralBSDF<Float, Spectrum>::Mixture &out) const override {
        if (!m_index)
            return BispectralBSDF<Float, Spectrum>::fluorescence_local(si, out);
        size_t k = material(si);
        out[0] = { fluorescence_at(si), k, 1.0, 1.0 };
        return 1;
    }

    size_t fluorescence_models() const override { return m_index ? m_models.size() : 0; }

    const fluo::Fluorescence *fluorescence_model(size_t i) const override {
        return i < m_models.size() ? &fluo::measured_fluorescence(*m_models[i]) : nullptr;
    }

    /// The diagonal alone (in RGB its sRGB, without the equal-energy reradiation).
    UnpolarizedSpectrum elastic_albedo(const SurfaceInteraction3f &si) const override {
        if constexpr (is_rgb_v<Spectrum>)
            return m_rgb_elastic[material(si)];
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
        oss << this->class_name() << "[" << std::endl;
        for (size_t i = 0; i < m_models.size(); ++i)
            oss << "  " << m_keys[i] << " = \"" << m_filenames[i] << "\"," << std::endl
                << "  model = " << std::string(fluo::measured_to_string(*m_models[i])) << "," << std::endl;
        if (m_index)
            oss << "  index = " << string::indent(m_index) << std::endl;
        oss << "]";
        return oss.str();
    }

private:
    /// Spectral: the diagonal at the hero wavelengths. RGB: the albedo under
    /// equal-energy light (diagonal plus reradiation), in Mitsuba's sRGB convention.
    UnpolarizedSpectrum albedo(const SurfaceInteraction3f &si) const {
        if constexpr (is_rgb_v<Spectrum>) {
            return m_rgb_albedo[material(si)];
        } else {
            std::array<float, 4> lambda = fluo_detail::wavelengths_of(si.wavelengths), out{};
            fluo::measured_elastic_albedo(*m_models[material(si)], fluo_detail::slice(lambda),
                                          fluo_detail::slice_mut(out));
            return UnpolarizedSpectrum(out[0], out[1], out[2], out[3]);
        }
    }

    /// The material at si: 0 without an index texture, else the index texture's value
    /// (its own eval_1: to_uv, filter) rounded to the nearest whole number, within range.
    size_t material(const SurfaceInteraction3f &si) const {
        if (!m_index)
            return 0;
        float v = m_index->eval_1(si, true);
        if (!std::isfinite(v))
            return 0;
        return (size_t) std::clamp(std::lround(v), 0l, (long) m_models.size() - 1);
    }

    const char *m_plugin;
    std::vector<std::string> m_keys, m_filenames; ///< "filename" or "filename0".., resolved paths
    std::vector<rust::Box<fluo::MeasuredModel>> m_models;
    ref<Texture> m_index; ///< material-index texture (null: one file)
    int m_representative = -1; ///< fluorescence(): the model with the longest emission, or none
    std::vector<Color3f> m_rgb_albedo, m_rgb_elastic;
};

NAMESPACE_END(mitsuba)
