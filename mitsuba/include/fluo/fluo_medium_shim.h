// The Mitsuba side of fluo's fluorescent participating media (fluo_qd_medium,
// fluo_dye_medium), written once: a Medium (optional density grid, host scattering
// sigma_s with any phase function, scale in metres per scene unit, a majorant shared by
// the hero wavelengths) plus the bispectral medium interface (fluo_bispectral_medium.h)
// over a Rust fluo::FluoMedium (MediumModel in core/src/model.rs). A plugin parses its own physical
// parameters, builds the Rust model and hands it to init().
#pragma once

#include <mitsuba/core/properties.h>
#include <mitsuba/render/medium.h>
#include <mitsuba/render/phase.h>
#include <mitsuba/render/volume.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <optional>
#include <sstream>
#include <string>

#include "fluo_bispectral_medium.h"
#include "fluo_common.h"

NAMESPACE_BEGIN(mitsuba)

NAMESPACE_BEGIN(fluo_detail)

/// A fluo medium's double property, rejecting non-numeric input with a message naming it.
inline double medium_double(const Properties &props, const char *plugin, const char *name, double def) {
    if (!props.has_property(name))
        return def;
    try {
        return props.get<double>(name);
    } catch (const std::exception &e) {
        Throw("%s: parameter \"%s\" must be a number (%s)", plugin, name, e.what());
    }
}

/// The majorant's floor relative to its largest value over the spectrum: null collisions
/// where the medium is (nearly) transparent, at most one per 10⁶ mean free paths of its
/// most opaque wavelength.
constexpr double MediumMajorantFloor = 1e-6;
/// Absolute floor (a medium with no absorbers and no scattering), inverse scene units.
constexpr double MediumMinMajorant = 1e-30;
/// Largest accepted peak absorption, inverse scene units: μa varies over the spectrum and
/// the majorant is shared by the hero wavelengths, so a wavelength the medium does not
/// absorb meets about this many null collisions per scene unit it crosses. Beyond it a
/// render does not finish in reasonable time (1e7 per unit: > 120 s for 16×16 at 8 spp).
constexpr double MediumMaxAbsorption = 1e5;

/// What every fluo medium parses in every variant: scale (metres per scene unit), the
/// optional density grid and the host's scattering σs, with their maxima (the majorant's
/// parts). Such a medium is never "homogeneous" to Mitsuba, even without a grid: volpath
/// then clips the ray at each tentative collision (ray.maxt = t), which is exact only
/// without null collisions, and these media have them (their majorant is shared by the
/// hero wavelengths). `bounded`: whether the density grid bounds the medium.
template <typename Float, typename Spectrum> struct MediumCommon {
    MI_IMPORT_TYPES(Volume)
    double scale = 1.0, max_density = 1.0, max_sigma_s = 0.0;
    bool bounded = false;
    /// No density grid and a constant σs: the extinction is the same everywhere.
    bool constant = false;
    ref<Volume> density, sigma_s;

    MediumCommon(const Properties &props, const char *plugin) {
        scale = medium_double(props, plugin, "scale", 1.0);
        if (!(scale > 0.0) || !std::isfinite(scale))
            Throw("%s: invalid parameter \"scale\" = %g: valid range is (0, inf) (metres per scene unit)", plugin,
                  scale);
        bounded = props.has_property("density");
        density = props.get_volume<Volume>("density", 1.f);
        max_density = (double) density->max();
        if (!(max_density >= 0.0) || !std::isfinite(max_density))
            Throw("%s: invalid parameter \"density\": its maximum %g must be finite and >= 0", plugin, max_density);
        sigma_s = props.get_volume<Volume>("sigma_s", 0.f);
        max_sigma_s = (double) sigma_s->max();
        if (!(max_sigma_s >= 0.0) || !std::isfinite(max_sigma_s))
            Throw("%s: invalid parameter \"sigma_s\": its maximum %g must be finite and >= 0", plugin,
                  max_sigma_s);
        constant = !bounded && dr::all(sigma_s->resolution() == ScalarVector3i(1, 1, 1));
    }

    /// The majorant's floor for a medium whose μa peaks at mu_max (1/m at density 1): where
    /// μa and σs vanish (beyond an absorption band) σt = 0, and volpath's mean null
    /// probability σn/μ̄ would be 0/0 (NaN) without it.
    double majorant_floor(double mu_max) const {
        return std::max(MediumMajorantFloor * (mu_max * max_density + max_sigma_s) * scale, MediumMinMajorant);
    }

    /// Refuse, at load, a medium whose tracking cannot finish: μa's peak mu_max (1/m at
    /// density 1) × the largest density × scale above MediumMaxAbsorption per scene unit.
    /// `what` names the model parameter that sets μa (e.g. "sigma_a = 1e9 1/m").
    void check_absorption(const char *plugin, double mu_max, const std::string &what) const {
        double per_unit = mu_max * max_density * scale;
        if (per_unit > MediumMaxAbsorption)
            Throw("%s: absorption too strong to track: μa peaks at %g per scene unit (%g 1/m from %s, x the "
                  "largest density %g, x scale %g m per unit), above the %g per scene unit that fluo's media "
                  "accept (delta tracking meets about that many null collisions per scene unit at the "
                  "wavelengths the medium does not absorb: the render would not finish). Lower %s, the "
                  "density or \"scale\" (metres per scene unit)",
                  plugin, per_unit, mu_max, what.c_str(), max_density, scale, MediumMaxAbsorption, what.c_str());
    }

    /// "Name[ model, scale, density, sigma_s, phase(, extra) ]".
    std::string describe(const char *name, const fluo::FluoMedium &model, const Object *phase,
                         const std::string &extra) const {
        std::ostringstream oss;
        oss << name << "[" << std::endl
            << "  model = " << std::string(fluo::medium_to_string(model)) << "," << std::endl
            << "  scale = " << scale << "," << std::endl
            << "  density_grid = " << bounded << "," << std::endl
            << "  density = " << string::indent(density) << "," << std::endl
            << "  sigma_s = " << string::indent(sigma_s) << "," << std::endl
            << "  phase_function = " << string::indent(phase) << (extra.empty() ? "" : ",") << std::endl;
        if (!extra.empty())
            oss << "  " << extra << std::endl;
        oss << "]";
        return oss.str();
    }
};

NAMESPACE_END(fluo_detail)

template <typename Float, typename Spectrum>
class FluoMediumShim : public Medium<Float, Spectrum>, public BispectralMedium<Float, Spectrum> {
public:
    MI_IMPORT_BASE(Medium, m_is_homogeneous, m_has_spectral_extinction, m_phase_function)
    MI_IMPORT_TYPES(Scene, Sampler, Texture, Volume)

    static constexpr double MinMajorant = fluo_detail::MediumMinMajorant;

    void traverse(TraversalCallback *cb) override {
        cb->put("density", m_common.density, ParamFlags::NonDifferentiable);
        cb->put("sigma_s", m_common.sigma_s, ParamFlags::NonDifferentiable);
        Base::traverse(cb);
    }

    /// A traversed update (density grid, σs) invalidates the per-thread caches.
    void parameters_changed(const std::vector<std::string> &keys) override {
        m_id = next_id();
        Base::parameters_changed(keys);
    }

    std::tuple<Mask, Float, Float> intersect_aabb(const Ray3f &ray) const override {
        if (!m_common.bounded)
            return { true, 0.f, dr::Infinity<Float> };
        return m_common.density->bbox().ray_intersect(ray);
    }

    UnpolarizedSpectrum get_majorant(const MediumInteraction3f &mi, Mask active) const override {
        DRJIT_MARK_USED(active);
        return majorant(collision_bound(mi, absorption(mi)));
    }

    std::tuple<UnpolarizedSpectrum, UnpolarizedSpectrum, UnpolarizedSpectrum>
    get_scattering_coefficients(const MediumInteraction3f &mi, Mask active) const override {
        this->warn_if_unmanaged(m_plugin);
        Float d = density(mi);
        UnpolarizedSpectrum mu_a = absorption(mi);
        UnpolarizedSpectrum sigma_s = m_common.sigma_s->eval(mi, active) * (Float) m_common.scale;
        UnpolarizedSpectrum sigma_t = mu_a * d * (Float) m_common.scale + sigma_s;
        UnpolarizedSpectrum sigma_n = dr::maximum(majorant(collision_bound(mi, mu_a)) - sigma_t, 0.f);
        return { sigma_s, sigma_n, sigma_t };
    }

    // ------------------------------------------------- the bispectral interface

    bool fluorescent() const override { return m_fluorescent; }
    fluo::Range lambda_range() const override { return m_range; }

    void shift_and_sample(const MediumInteraction3f &mei, const fluo::Range &range, const std::array<double, 4> &xi,
                          std::array<float, 4> &mu_f, std::array<fluo::Sample, 4> &samples) const override {
        mu_f.fill(0.f);
        samples.fill(fluo::Sample{ 0.0, 0.0 });
        if constexpr (is_spectral_v<Spectrum>) {
            double d = (double) density(mei);
            std::array<float, 4> lambda = fluo_detail::wavelengths_of(mei.wavelengths);
            fluo::medium_shift_and_sample(**m_model, fluo_detail::slice(lambda),
                                          rust::Slice<const double>(xi.data(), xi.size()), range,
                                          fluo_detail::slice_mut(mu_f),
                                          rust::Slice<fluo::Sample>(samples.data(), samples.size()));
            for (float &v : mu_f)
                v = d > 0.0 ? (float) (v * d * m_common.scale) : 0.f;
        }
    }

    void source_bound(const MediumInteraction3f &mei, std::array<float, 4> &out) const override {
        out.fill(0.f);
        if constexpr (is_spectral_v<Spectrum>) {
            double d = (double) density(mei);
            if (!(d > 0.0))
                return;
            const Rates &r = rates(mei);
            for (size_t j = 0; j < 4; ++j)
                out[j] = (float) (r.mu_f[j] * d * m_common.scale);
        }
    }

    void reduced_operators(const fluo::TransportBasis &t, rust::Slice<double> a,
                           rust::Slice<double> f) const override {
        fluo::medium_reduced(**m_model, t, a, f);
        for (double &v : a)
            v *= m_common.scale;
        for (double &v : f)
            v *= m_common.scale;
    }

    bool constant_extinction(const MediumInteraction3f &mei, UnpolarizedSpectrum &sigma_t) const override {
        if (!m_common.constant)
            return false;
        sigma_t = absorption(mei) * (Float) m_common.scale + m_common.sigma_s->eval(mei, true) * (Float) m_common.scale;
        return true;
    }

    Float density_at(const MediumInteraction3f &mei) const override {
        return density(mei);
    }

protected:
    /// Parse what every fluo medium shares (fluo_detail::MediumCommon); the phase
    /// function is Medium's.
    FluoMediumShim(const Properties &props, const char *plugin)
        : Base(props), m_plugin(plugin), m_common(props, plugin) {
        m_is_homogeneous = false; // MediumCommon says why
        m_has_spectral_extinction = true;
    }

    /// Adopt the plugin's Rust model and derive what the render needs from it.
    /// `what`: the parameters that set μa, for the absorption check's message.
    void init(rust::Box<fluo::FluoMedium> model, const std::string &what) {
        m_model = std::move(model);
        m_fluorescent = fluo::medium_is_fluorescent(**m_model);
        m_range = fluo::medium_lambda_range(**m_model);
        fluo::Rgb a = fluo::medium_absorption_rgb(**m_model);
        m_mu_a_rgb = { a.r, a.g, a.b };
        double mu_max = 0.0; // μa's peak, for the majorant's floor
        std::array<float, 4> lambda{}, mu{};
        for (int l = 200; l <= 1200; l += 4) {
            for (size_t j = 0; j < 4; ++j)
                lambda[j] = (float) (l + j);
            fluo::medium_absorption(**m_model, fluo_detail::slice(lambda), fluo_detail::slice_mut(mu));
            for (float v : mu)
                mu_max = std::max(mu_max, (double) v);
        }
        m_common.check_absorption(m_plugin, mu_max, what);
        m_majorant_floor = m_common.majorant_floor(mu_max);
        m_mu_a_max = std::max({ fluo::medium_grid_absorption_max(**m_model), m_mu_a_rgb[0], m_mu_a_rgb[1],
                                m_mu_a_rgb[2] });
        m_mu_f_max = m_fluorescent ? fluo::medium_grid_source_max(**m_model) : 0.0;
    }

    std::string describe(const char *name) const { return m_common.describe(name, **m_model, m_phase_function.get(), ""); }

private:
    /// μ̄ = max over the hero wavelengths of (max density · μa + max σs) · scale (in RGB:
    /// over the whole spectrum), at least
    /// the floor (inverse scene units), the same for every wavelength: μa varies a
    /// hundredfold over the spectrum, and a per-wavelength majorant would let the first
    /// hero wavelength (which samples the distance) fly through where the others collide,
    /// leaving their collisions (and fluorescence) to rare, huge weights.
    UnpolarizedSpectrum majorant(const UnpolarizedSpectrum &mu_a) const {
        UnpolarizedSpectrum m = (mu_a * (Float) m_common.max_density + (Float) m_common.max_sigma_s) * (Float) m_common.scale;
        if constexpr (is_rgb_v<Spectrum>) {
            // the spectrum's maximum bounds the bands of any reduced transport; once
            // fluo_volpath has prepared one, the maximum over its bands (and μa's RGB)
            double band = this->band_absorption_max();
            double rgb = std::max({ m_mu_a_rgb[0], m_mu_a_rgb[1], m_mu_a_rgb[2] }) * m_common.scale;
            double mu = band > 0.0 ? std::max(band, rgb) : m_mu_a_max * m_common.scale;
            m = dr::maximum(m, UnpolarizedSpectrum((Float) (mu * m_common.max_density + m_common.max_sigma_s * m_common.scale)));
        }
        return UnpolarizedSpectrum(dr::maximum(dr::max(m), (Float) m_majorant_floor));
    }

    /// What the majorant must cover per wavelength, 1/m at density 1: μa and, when
    /// fluo_volpath asks for a source rate ρ (fluo_detail::source_rate_request, inverse
    /// scene units), the fluorescent source μf(λ) (over the medium's whole range) up to
    /// ρ: its real collisions re-emit at λ with weight σs + μf also where μa(λ) = 0, and
    /// without tentative collisions there dots transparent at their own emission band
    /// would seldom be hit at all. Capped at ρ (about one per flight), the majorant grows
    /// only where the path's wavelengths are not absorbed.
    UnpolarizedSpectrum collision_bound(const MediumInteraction3f &mi, const UnpolarizedSpectrum &mu_a) const {
        double rate = fluo_detail::source_rate_request();
        if (!m_fluorescent || !(rate > 0.0) || !(m_common.max_density > 0.0))
            return mu_a;
        Float cap = (Float) (rate / (m_common.max_density * m_common.scale)); // 1/m at density 1
        UnpolarizedSpectrum out = mu_a;
        if constexpr (is_spectral_v<Spectrum>) {
            const Rates &r = rates(mi);
            for (size_t j = 0; j < dr::size_v<UnpolarizedSpectrum>; ++j)
                out[j] = dr::maximum(out[j], dr::minimum(r.mu_f[j], cap));
        } else {
            for (size_t j = 0; j < dr::size_v<UnpolarizedSpectrum>; ++j)
                out[j] = dr::maximum(out[j], dr::minimum((Float) m_mu_f_max, cap));
        }
        return out;
    }

    /// The density at mi.p (1 without a grid). A tentative collision asks for it up to
    /// three times at one point (coefficients, source bound, shift): one grid lookup
    /// per point, per thread.
    Float density(const Interaction3f &mi) const {
        if (!m_common.bounded)
            return Float(1.f);
        struct Last {
            uint64_t owner = 0;
            Point3f p;
            Float d = 0.f;
        };
        thread_local Last last;
        if (last.owner != m_id || dr::any(last.p != mi.p)) {
            last.owner = m_id;
            last.p = mi.p;
            last.d = m_common.density->eval_1(mi, true);
        }
        return last.d;
    }

    /// μa and μf (whole range) at a path's four wavelengths, 1/m at density 1. A flight
    /// keeps its wavelengths over all of its tentative collisions, each of which asks
    /// for them 2-3 times: one Rust call per new set of wavelengths, per thread.
    struct Rates {
        uint64_t owner = 0; ///< m_id of the medium (0: empty)
        std::array<float, 4> lambda{}, mu_a{}, mu_f{};
    };
    const Rates &rates(const MediumInteraction3f &mi) const {
        thread_local Rates cache;
        std::array<float, 4> lambda = fluo_detail::wavelengths_of(mi.wavelengths);
        if (cache.owner != m_id || cache.lambda != lambda) {
            cache.owner = m_id;
            cache.lambda = lambda;
            fluo::medium_absorption(**m_model, fluo_detail::slice(lambda), fluo_detail::slice_mut(cache.mu_a));
            cache.mu_f.fill(0.f);
            if (m_fluorescent)
                fluo::medium_shift_coefficients(**m_model, fluo_detail::slice(lambda), m_range,
                                                fluo_detail::slice_mut(cache.mu_f));
        }
        return cache;
    }

    /// μa at the interaction's wavelengths (spectral) or its sRGB (RGB), 1/m, density 1.
    UnpolarizedSpectrum absorption(const MediumInteraction3f &mi) const {
        UnpolarizedSpectrum out(0.f);
        if constexpr (is_spectral_v<Spectrum>) {
            const Rates &r = rates(mi);
            for (size_t j = 0; j < dr::size_v<UnpolarizedSpectrum>; ++j)
                out[j] = r.mu_a[j];
        } else {
            for (size_t j = 0; j < dr::size_v<UnpolarizedSpectrum> && j < 3; ++j)
                out[j] = (float) m_mu_a_rgb[j];
        }
        return out;
    }

    const char *m_plugin;
    /// Unique per medium object and parameter state (the key of the per-thread caches).
    uint64_t m_id = next_id(); ///< renewed by parameters_changed (its caches' key)
    static uint64_t next_id() {
        static std::atomic<uint64_t> counter{ 0 };
        return ++counter;
    }
    std::optional<rust::Box<fluo::FluoMedium>> m_model;
    /// scale, density grid, σs and their maxima
    fluo_detail::MediumCommon<Float, Spectrum> m_common;
    double m_majorant_floor = MinMajorant;
    /// max of μa over reduced transport's wavelengths and of its RGB channels, 1/m: the RGB
    /// variants' majorant; and the max of μf there (collision_bound).
    double m_mu_a_max = 0.0, m_mu_f_max = 0.0;
    bool m_fluorescent = false;
    fluo::Range m_range{ 0, 0 };
    std::array<double, 3> m_mu_a_rgb{};
};

NAMESPACE_END(mitsuba)
