// fluo's fluorescent participating media (fluo_qd_medium, fluo_dye_medium) in every
// variant: the parameters they share (MediumCommon), a Mitsuba Medium with Dr.Jit types
// that interpolates what Rust baked at load time (fluo::medium_jit_tables; the
// MediumJitTables docs in core/src/model.rs hold the contract), and the interface
// fluo_volpath reaches it through per lane (dr::dispatch over the media).
#pragma once

#include <mitsuba/core/properties.h>
#include <mitsuba/render/interaction.h>
#include <mitsuba/render/medium.h>
#include <mitsuba/render/phase.h>
#include <mitsuba/render/volume.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <functional>
#include <optional>
#include <sstream>
#include <string>
#include <tuple>
#include <vector>

#include "fluo_bispectral_medium.h"
#include "fluo_common.h"
#include "fluo_bispectral.h"

NAMESPACE_BEGIN(mitsuba)
NAMESPACE_BEGIN(fluo_detail)

/// A traversed parameter of a medium's model (FluoMediumBase::init): its name, its value
/// as loaded, and the step h of its derivative's central differences (h·max(|value|, 1);
/// the first parameter is the absorber's amount, linear, whose step is unused).
struct MediumParam {
    const char *name;
    double value, step;
};

/// A medium's Rust model for its parameters' values (in MediumParam order).
using MediumBuild = std::function<rust::Box<fluo::FluoMedium>(const std::vector<double> &)>;

/// A medium plugin's MediumBuild: its parsed configuration `c` with the fields `fields`
/// set, made by `make`.
template <typename Config, typename Make>
MediumBuild medium_builder(const char *plugin, const Config &c, std::vector<double Config::*> fields, Make make) {
    return [plugin, c, fields, make](const std::vector<double> &v) {
        Config at = c;
        for (size_t i = 0; i < fields.size() && i < v.size(); ++i)
            at.*fields[i] = v[i];
        return rust_call(plugin, [&] { return make(at); });
    };
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
    ref<Volume> density, sigma_s;

    MediumCommon(const Properties &props, const char *plugin) {
        scale = get_float<double>(plugin, props, "scale", 1.0);
        if (!(scale > 0.0) || !std::isfinite(scale))
            Throw("%s: invalid parameter \"scale\" = %g: valid range is (0, inf) (metres per scene unit)", plugin,
                  scale);
        density = props.get_volume<Volume>("density", 1.f);
        // a grid bounds the medium; a constant (<float name="density">, Mitsuba's constvolume,
        // whose box is the unit cube) scales it everywhere, as the default 1 does
        bounded = props.has_property("density") && std::string_view(density->class_name()) != "ConstVolume";
        sigma_s = props.get_volume<Volume>("sigma_s", 0.f);
        // a density scales the dye's concentration: one channel (a 3-channel grid rendered
        // in RGB variants and failed at render time in spectral ones), asked once here
        try {
            (void) density->eval_1(dr::zeros<Interaction3f>(), true);
        } catch (const std::exception &e) {
            Throw("%s: invalid parameter \"density\": the density must have one channel (a scalar grid "
                  "or a float): %s",
                  plugin, e.what());
        }
        refresh(plugin);
    }

    /// Read (at load, and after an update through mi.traverse) and check the maxima of the
    /// density and σs, which the majorant is made of.
    void refresh(const char *plugin) {
        double d = (double) density->max(), s = (double) sigma_s->max();
        if (!(d >= 0.0) || !std::isfinite(d))
            Throw("%s: invalid parameter \"density\": its maximum %g must be finite and >= 0", plugin, d);
        if (!(s >= 0.0) || !std::isfinite(s))
            Throw("%s: invalid parameter \"sigma_s\": its maximum %g must be finite and >= 0", plugin, s);
        // every voxel (the maxima let a NaN or negative one through) and a constant's value
        // at the wavelengths (an RGB σs with a NaN channel): finite and >= 0
        constexpr double inf = std::numeric_limits<double>::infinity();
        check_stored_values<Float>(plugin, "density", density.get(), 0.0, inf, true);
        check_stored_values<Float>(plugin, "sigma_s", sigma_s.get(), 0.0, inf, true);
        auto constant_of = [](const Volume *v) { return dr::all(v->resolution() == ScalarVector3i(1, 1, 1)); };
        auto at = [](const Wavelength &w) {
            Interaction3f it = dr::zeros<Interaction3f>();
            it.wavelengths = w;
            return it;
        };
        if (constant_of(density.get()))
            check_probed_values<Float, Spectrum>(plugin, "density", 0.0, inf, [&](const Wavelength &w) {
                return dr::Array<Float, 1>(density->eval_1(at(w), true));
            });
        if (constant_of(sigma_s.get()))
            check_probed_values<Float, Spectrum>(plugin, "sigma_s", 0.0, inf,
                                                 [&](const Wavelength &w) { return sigma_s->eval(at(w), true); });
        max_density = d;
        max_sigma_s = s;
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


/// What fluo_volpath needs of a fluorescent medium, per lane, in every variant
/// (spectral variants: wavelength shifting; RGB variants: the reduced operators).
template <typename Float, typename Spectrum> class BispectralMedium : public ManagedMedium {
public:
    MI_IMPORT_TYPES()
    using WMask = dr::mask_t<UnpolarizedSpectrum>;

    /// Host: whether the medium re-emits anything from [lo, hi] (the lights' range).
    virtual bool jit_fluorescent(double lo, double hi) const = 0;
    /// Host: [λmin, λmax], nm, where it absorbs-to-re-emit and emits.
    virtual fluo::Range jit_range() const = 0;

    /// μa(λ) and μf(λ | [lo, hi]) at the wavelengths, 1/m at density 1: what a flight's
    /// tentative collisions need (a flight keeps its wavelengths; fluo_volpath asks once per
    /// flight). RGB variants: μa's linear sRGB and μf = 0.
    virtual std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum> jit_rates(const Wavelength &lambda, double lo,
                                                                          double hi, Mask active) const = 0;

    /// A tentative collision along `ray` (Medium::sample_interaction's fields and delta
    /// tracking with uniform number u) given the flight's jit_rates (RGB variants: μa's
    /// sRGB, or a larger per-channel bound the majorant must cover: the reduced transport
    /// passes its bands' largest absorption too), with a majorant that
    /// also covers the fluorescent source μf up to `rate` (inverse scene units per lane; 0:
    /// none, +inf: all of it), times `margin` (≥ 1: a majorant standing clear of σt). Returns
    /// the interaction, μf at its point (inverse scene units, density and scale included)
    /// and the factor d = density·scale that turns 1/m at density 1 into inverse scene
    /// units there.
    virtual std::tuple<MediumInteraction3f, UnpolarizedSpectrum, Float>
    jit_sample_interaction(const Ray3f &ray, const Float &u, const Float &rate, const UnpolarizedSpectrum &mu_a,
                           const UnpolarizedSpectrum &mu_f, float margin, Mask active) const = 0;

    /// The factor d of jit_sample_interaction at mei's point, with the gradients of the
    /// density and the amount (fluo_prbvolpath's replay differentiates it at a detached point).
    virtual Float jit_density(const MediumInteraction3f &mei, Mask active) const = 0;

    /// Per wavelength λo of mei: an excitation wavelength λi ∝ μa(λi) f(λi → λo) over
    /// [lo, hi] drawn with u (exactly, so that a shift weighs μf), where one exists, and the
    /// relative derivative of that density at λi (1 in value; its derivative where a
    /// parameter reshapes μa: a shift's weight is μf times it).
    virtual std::tuple<Wavelength, WMask, UnpolarizedSpectrum>
    jit_excitation(const MediumInteraction3f &mei, const Wavelength &u, double lo, double hi,
                   Mask active) const = 0;

    /// Host, RGB variants: the absorption A and reradiation F reduced for the transport
    /// basis `t` (fluo::medium_reduced), K×K row major each, 1/m at density 1: at a point,
    /// μa acts on basis coefficients as d·A and light c re-emits d·F·c/(4π) per steradian
    /// (d from jit_sample_interaction).
    virtual void jit_reduced_operators(const fluo::TransportBasis &t, rust::Slice<double> a,
                                       rust::Slice<double> f) const = 0;

    /// Host, at a render's start with the lights' range [lo, hi] (as jit_rates gets it): the
    /// model's parameters that carry gradients (a shape of μa or of the emission: its tables
    /// then carry value + (θ − detach(θ))·∂/∂θ), and what the range fixes, as kernel inputs.
    virtual void jit_prepare(double lo, double hi) const = 0;

    /// A parameter carrying a gradient, RGB variants: θ − detach(θ) and the derivatives of
    /// jit_reduced_operators' A and F in θ (K×K each).
    struct ReducedTangent {
        Float delta;
        std::vector<double> a, f;
    };
    /// Host, RGB variants, after jit_prepare: one ReducedTangent per parameter carrying a
    /// gradient (none without).
    virtual std::vector<ReducedTangent> jit_reduced_tangents(const fluo::TransportBasis &t) const = 0;
};

NAMESPACE_END(fluo_detail)

/// The Medium of fluo_qd_medium and fluo_dye_medium in every variant: the common
/// parameters (MediumCommon), μa and the emission from Rust's tables. A plugin parses its
/// own physical parameters, builds the Rust model and hands it to init(). Spectral
/// variants: μa at the path's wavelengths; RGB variants: μa's linear sRGB.
template <typename Float, typename Spectrum>
class FluoMediumBase : public Medium<Float, Spectrum>, public fluo_detail::BispectralMedium<Float, Spectrum> {
public:
    MI_IMPORT_BASE(Medium, m_is_homogeneous, m_has_spectral_extinction, m_phase_function)
    MI_IMPORT_TYPES(Scene, Sampler, Texture, Volume)
    using WMask = dr::mask_t<UnpolarizedSpectrum>;
    using Grid = fluo_detail::LaneGrid<Float>;
    using Cell = typename Grid::Cell;
    using FloatStorage = DynamicBuffer<Float>;
    static constexpr size_t NW = dr::size_v<UnpolarizedSpectrum>;
    /// The majorant under Mitsuba's medium interface over the shared one (majorant()).
    static constexpr float NativeMajorantFactor = 2.f;

    void traverse(TraversalCallback *cb) override {
        m_record.arm(this);
        // differentiable through fluo_volpath (its tracking weighs each event by its rate over
        // a detached probability, under a detached majorant)
        for (size_t i = 0; i < m_params.size(); ++i)
            cb->put(m_params[i].name, m_values[i], ParamFlags::Differentiable);
        cb->put("density", m_common.density, ParamFlags::Differentiable);
        cb->put("sigma_s", m_common.sigma_s, ParamFlags::Differentiable);
        Base::traverse(cb);
    }

    std::tuple<Mask, Float, Float> intersect_aabb(const Ray3f &ray) const override {
        if (!m_common.bounded)
            return { true, 0.f, dr::Infinity<Float> };
        return m_common.density->bbox().ray_intersect(ray);
    }

    UnpolarizedSpectrum get_majorant(const MediumInteraction3f &mi, Mask active) const override {
        return majorant(absorption(mi.wavelengths, active), active);
    }

    std::tuple<UnpolarizedSpectrum, UnpolarizedSpectrum, UnpolarizedSpectrum>
    get_scattering_coefficients(const MediumInteraction3f &mi, Mask active) const override {
        this->warn_if_unmanaged(m_plugin, m_fluorescent);
        UnpolarizedSpectrum mu_a = absorption(mi.wavelengths, active);
        UnpolarizedSpectrum sigma_s = m_common.sigma_s->eval(mi, active) * (Float) m_common.scale;
        UnpolarizedSpectrum sigma_t = mu_a * density(mi, active) * (Float) m_common.scale + sigma_s;
        UnpolarizedSpectrum sigma_n = null_rate(majorant(mu_a, active), sigma_t);
        return { sigma_s, sigma_n, sigma_t };
    }

    // ------------------------------------------------- the bispectral interface

    bool jit_fluorescent(double lo, double hi) const override {
        if constexpr (!is_spectral_v<Spectrum>)
            return m_fluorescent && lo < hi;
        return m_fluorescent && std::max(lo, m_range.lo) < std::min(hi, m_range.hi);
    }
    fluo::Range jit_range() const override { return m_range; }

    std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum> jit_rates(const Wavelength &lambda, double lo, double hi,
                                                                  Mask active) const override {
        UnpolarizedSpectrum mu_a(0.f), mu_f(0.f);
        if constexpr (is_spectral_v<Spectrum>) {
            auto [a, b] = excitation_interval(lo, hi);
            for (size_t j = 0; j < NW; ++j) {
                Cell c = m_grid.cell(lambda[j], active);
                mu_a[j] = mu_a_in(c, active);
                mu_f[j] = source(lambda[j], c, a, b, active);
            }
        } else {
            (void) lo, (void) hi;
            mu_a = absorption(lambda, active);
        }
        return { mu_a, mu_f };
    }

    std::tuple<MediumInteraction3f, UnpolarizedSpectrum, Float>
    jit_sample_interaction(const Ray3f &ray, const Float &u, const Float &rate, const UnpolarizedSpectrum &mu_a,
                           const UnpolarizedSpectrum &mu_f, float margin, Mask active) const override {
        MediumInteraction3f mi = dr::zeros<MediumInteraction3f>();
        mi.wi = -ray.d;
        mi.sh_frame = Frame3f(mi.wi);
        mi.time = ray.time;
        mi.wavelengths = ray.wavelengths;
        auto [hit, mint, maxt] = intersect_aabb(ray);
        active &= hit && (dr::isfinite(mint) || dr::isfinite(maxt));
        mint = dr::select(active, dr::maximum(mint, 0.f), 0.f);
        maxt = dr::select(active, dr::minimum(ray.maxt, maxt), dr::Infinity<Float>);
        // the requested rate in 1/m at density 1
        Float cap = rate * m_inv_rate_unit;
        UnpolarizedSpectrum m_bar = majorant(dr::maximum(mu_a, dr::minimum(mu_f, cap)), active, false) * margin;
        Float t = mint - dr::log(1.f - u) / m_bar[0];
        Mask valid = active && t <= maxt;
        mi.t = dr::select(valid, t, dr::Infinity<Float>);
        mi.p = ray(t);
        mi.medium = this;
        mi.mint = mint;
        Float d = density(mi, valid) * (float) m_common.scale;
        mi.sigma_s = m_common.sigma_s->eval(mi, valid) * (Float) m_common.scale;
        mi.sigma_t = mu_a * d + mi.sigma_s;
        mi.sigma_n = null_rate(m_bar, mi.sigma_t);
        mi.combined_extinction = m_bar;
        return { mi, dr::select(valid, mu_f * d, 0.f), dr::select(valid, d, 0.f) };
    }

    Float jit_density(const MediumInteraction3f &mei, Mask active) const override {
        return density(mei, active) * (float) m_common.scale;
    }

    std::tuple<Wavelength, WMask, UnpolarizedSpectrum> jit_excitation(const MediumInteraction3f &mei,
                                                                      const Wavelength &u, double lo, double hi,
                                                                      Mask active) const override {
        Wavelength li = mei.wavelengths;
        WMask ok = false;
        UnpolarizedSpectrum rel(1.f);
        if constexpr (is_spectral_v<Spectrum>) {
            auto [a, b] = excitation_interval(lo, hi);
            if (!(a < b))
                return { li, ok, rel };
            Float ca = dr::detach(cum_at(a));
            uint32_t search_bound = 1;
            while (search_bound < m_grid.n - 1)
                search_bound <<= 1;
            for (size_t j = 0; j < NW; ++j) {
                Float top = dr::minimum(mei.wavelengths[j], (float) b);
                Mask live = active && top > (float) a;
                Float cb_ad = cumulative(top, m_grid.cell(top, live), live);
                Float cb = dr::detach(cb_ad); // (sampling)
                Float target = dr::fmadd(u[j], cb - ca, ca);
                // the cell holding `target`: the last k with cum[k] <= target (over a power of
                // two of nodes: an update that bakes another node count keeps the kernel)
                UInt32 k = dr::binary_search<UInt32>(1, search_bound, [&](const UInt32 &i) {
                               return i < m_grid.v_n - 1 &&
                                      fluo_detail::fetch<Float>(m_cum, dr::minimum(i, m_grid.v_n - 1), live) <= target;
                           }) - 1;
                Float x0 = fluo_detail::fetch<Float>(m_grid.nodes, k, live), x1 = fluo_detail::fetch<Float>(m_grid.nodes, k + 1, live);
                Float f0 = fluo_detail::fetch<Float>(m_mu_a, k, live), f1 = fluo_detail::fetch<Float>(m_mu_a, k + 1, live);
                Float off = fluo_detail::linear_cell_inverse(f0, f1, x1 - x0, target - fluo_detail::fetch<Float>(m_cum, k, live));
                li[j] = dr::clip(x0 + off, (float) a, top);
                ok[j] = live && cb > ca && dr::isfinite(cb);
                if (m_ad.on) // μa(λi)/(C(top) − C(a)) with the parameters' derivatives
                    rel[j] = fluo_detail::relative(
                        mu_a_in(m_grid.cell(li[j], live), live) /
                        dr::select(ok[j], cb_ad - cum_at(a), 1.f));
            }
        } else {
            (void) u, (void) lo, (void) hi, (void) active;
        }
        return { li, ok, rel };
    }

    void jit_reduced_operators(const fluo::TransportBasis &t, rust::Slice<double> a,
                               rust::Slice<double> f) const override {
        fluo::medium_reduced(**m_model, t, a, f);
    }

    void jit_prepare(double lo, double hi) const override {
        m_ad = {};
        if constexpr (dr::is_diff_v<Float>) {
            for (size_t p = 1; p < m_params.size(); ++p) {
                if (!dr::grad_enabled(m_values[p]))
                    continue;
                const Tangent &t = tangent(p);
                if (!m_fluorescent && t.emits)
                    Throw("%s: the derivative in \"%s\" (= %g) would make a medium that re-emits nothing "
                          "re-emit, and fluo_volpath samples no re-emission where none happens (the "
                          "derivative would come out without it): differentiate from a value where the "
                          "medium fluoresces (e.g. quantum_yield 1e-3 instead of 0)",
                          m_plugin, m_params[p].name, m_hosts[p]);
                Float delta = m_values[p] - dr::detach(m_values[p]);
                if (!m_ad.on) {
                    m_ad = { true, m_mu_a, m_cum, m_emission, {} };
                    for (size_t j = 0; j < 3; ++j)
                        m_ad.rgb[j] = Float((float) m_mu_a_rgb[j]);
                }
                m_ad.mu_a = dr::fmadd(t.mu_a, delta, m_ad.mu_a);
                m_ad.cum = dr::fmadd(t.cum, delta, m_ad.cum);
                m_ad.emission = dr::fmadd(t.emission, delta, m_ad.emission);
                for (size_t j = 0; j < 3; ++j)
                    m_ad.rgb[j] = dr::fmadd(Float((float) t.rgb[j]), delta, m_ad.rgb[j]);
            }
        }
        prepare_range(lo, hi); // (from the tables with their derivatives, where attached)
        if constexpr (dr::is_diff_v<Float>)
            if (m_ad.on) // evaluated here, not where a traced loop first gathers from them
                dr::eval(m_ad.mu_a, m_ad.cum, m_ad.emission, m_ad.rgb[0], m_ad.rgb[1], m_ad.rgb[2], m_range_at.ca,
                         m_range_at.cb);
    }

    std::vector<typename fluo_detail::BispectralMedium<Float, Spectrum>::ReducedTangent>
    jit_reduced_tangents(const fluo::TransportBasis &t) const override {
        std::vector<typename fluo_detail::BispectralMedium<Float, Spectrum>::ReducedTangent> out;
        if constexpr (dr::is_diff_v<Float>) {
            size_t k2 = (size_t) fluo::transport_size(t);
            k2 *= k2;
            for (size_t p = 1; p < m_params.size(); ++p) {
                if (!dr::grad_enabled(m_values[p]))
                    continue;
                auto d = derivative(p, [&](const fluo::FluoMedium &m) {
                    std::vector<double> af(2 * k2);
                    fluo::medium_reduced(m, t, rust::Slice<double>(af.data(), k2),
                                         rust::Slice<double>(af.data() + k2, k2));
                    return af;
                });
                out.push_back({ m_values[p] - dr::detach(m_values[p]), std::vector<double>(d.begin(), d.begin() + k2),
                                std::vector<double>(d.begin() + k2, d.end()) });
            }
        }
        return out;
    }

protected:
    FluoMediumBase(const Properties &props, const char *plugin)
        : Base(props), m_plugin(plugin), m_common(props, plugin) {
        m_is_homogeneous = false; // MediumCommon says why
        m_has_spectral_extinction = true;
    }

    /// Adopt the plugin's Rust model and bake its tables. `params`: the model's traversed
    /// parameters, the absorber's amount first (μa and the re-emission are linear in it);
    /// `build(values)`: the model at those values, validated by Rust; `what`: the parameters
    /// that set μa, for the absorption check's message. The tables are baked at the amount
    /// (at 1 where it is 0) and the density carries the ratio, so an update of the amount
    /// through mi.traverse re-bakes nothing and recompiles nothing; an update of another
    /// parameter bakes the tables again.
    void init(std::vector<fluo_detail::MediumParam> params, fluo_detail::MediumBuild build, const std::string &what) {
        m_params = std::move(params);
        m_build = std::move(build);
        m_what = what;
        m_values.clear();
        m_hosts.clear();
        for (const fluo_detail::MediumParam &p : m_params) {
            m_values.push_back(dr::opaque<Float>((float) p.value));
            m_hosts.push_back(p.value);
        }
        if (!(m_hosts[0] > 0.0))
            (void) m_build(m_hosts); // validated as given (the tables are baked at 1)
        bake(m_hosts[0]);
        refresh_majorant();
    }

    /// The tables at the host values with the absorber's amount `amount` (1 where it is 0;
    /// the density carries the ratio to the actual amount).
    void bake(double amount) {
        m_amount_baked = amount > 0.0 ? amount : 1.0;
        m_inv_amount_baked = dr::opaque<Float>((float) (1.0 / m_amount_baked));
        m_baked = m_hosts;
        m_baked[0] = m_amount_baked;
        m_model = m_build(m_baked);
        m_fluorescent = fluo::medium_is_fluorescent(**m_model);
        m_range = fluo::medium_lambda_range(**m_model);
        fluo::Rgb rgb = fluo::medium_absorption_rgb(**m_model);
        m_mu_a_rgb = { rgb.r, rgb.g, rgb.b };
        fluo::MediumJitTables t = fluo::medium_jit_tables(**m_model);
        if (t.lambda.size() < 2 || t.mu_a.size() != t.lambda.size() || t.cum.size() != t.lambda.size() ||
            t.emission_lambda.size() < 2 || t.emission.size() != t.emission_lambda.size())
            Throw("%s: the medium's tables have %zu nodes, %zu emission nodes (at least 2 each expected)", m_plugin,
                  t.lambda.size(), t.emission_lambda.size());
        m_grid.set(std::vector<double>(t.lambda.begin(), t.lambda.end()));
        m_mu_a_host.assign(t.mu_a.begin(), t.mu_a.end());
        m_cum_host.assign(t.cum.begin(), t.cum.end());
        m_mu_a = fluo_detail::load_floats<FloatStorage>(t.mu_a);
        m_cum = fluo_detail::load_floats<FloatStorage>(t.cum);
        m_emission = fluo_detail::load_floats<FloatStorage>(t.emission);
        m_egrid.set(std::vector<double>(t.emission_lambda.begin(), t.emission_lambda.end()));
        m_mu_max = *std::max_element(m_mu_a_host.begin(), m_mu_a_host.end());
        m_rgb_mu_max = std::max({ fluo::medium_grid_absorption_max(**m_model), m_mu_a_rgb[0], m_mu_a_rgb[1],
                                  m_mu_a_rgb[2] });
        m_tangents.assign(m_params.size(), std::nullopt);
        m_ad = {};
        m_range_at = {};
    }

    /// After a change of the amount, the density or σs: the absorption check and the
    /// majorant's parts (kernel inputs, so that an update recompiles nothing), from the
    /// host values. μa's tables are per baked amount: their maxima scale by the ratio.
    void refresh_majorant() {
        const double ratio = m_hosts[0] / m_amount_baked, d = m_common.max_density * ratio;
        m_common.check_absorption(m_plugin, m_mu_max * ratio, m_what);
        m_maj_density = dr::opaque<Float>((float) d);
        m_maj_sigma_s = dr::opaque<Float>((float) m_common.max_sigma_s);
        m_maj_floor = dr::opaque<Float>((float) m_common.majorant_floor(m_mu_max * ratio));
        m_maj_rgb = dr::opaque<Float>((float) ((m_rgb_mu_max * d + m_common.max_sigma_s) * m_common.scale));
        m_inv_rate_unit = dr::opaque<Float>((float) (1.0 / std::max(d * m_common.scale, 1e-300)));
    }

    /// An update (mi.traverse) of the model's parameters, the density or σs: the values
    /// validated by Rust (the model rebuilt with them), the tables baked again where a
    /// parameter other than the amount changed, the majorant's maxima, the absorption check
    /// and the majorant's floor following (a stale majorant biases tracking). A refused
    /// update puts the values back (fluo_detail::UpdateRecord), the tables with them.
    void parameters_changed(const std::vector<std::string> &keys) override {
        m_record.update(this, m_hosts, [&] {
            m_ad = {}; // (jit_prepare attaches them again at the next render)
            m_range_at = {};
            std::vector<double> v(m_hosts.size());
            for (size_t i = 0; i < v.size(); ++i)
                v[i] = fluo_detail::updated_param(m_plugin, m_params[i].name, m_values[i], m_hosts[i]);
            if (v != m_hosts)
                (void) m_build(v);
            m_hosts = v;
            // (at the amount baked before: a refused update's restore bakes the same tables)
            if (!std::equal(v.begin() + 1, v.end(), m_baked.begin() + 1))
                bake(m_amount_baked);
            m_common.refresh(m_plugin);
            refresh_majorant();
            for (Float &x : m_values) // kernel inputs, not literals: the next value reuses the kernel
                if (!dr::grad_enabled(x))
                    dr::make_opaque(x);
        });
        Base::parameters_changed(keys);
    }

    std::string describe(const char *name) const {
        std::ostringstream extra;
        extra << m_params[0].name << " = " << m_hosts[0] << " (tables at " << m_amount_baked << "), tables = "
              << m_grid.n << " absorption nodes, " << m_egrid.n << " emission nodes";
        return m_common.describe(name, **m_model, m_phase_function.get(), extra.str());
    }

private:
    /// A parameter's derivative tables (on this bake's nodes) and μa's sRGB's derivative.
    struct Tangent {
        FloatStorage mu_a, cum, emission;
        std::array<double, 3> rgb{};
        bool emits = false; ///< the emission's derivative is not 0 everywhere
    };

    /// ∂f/∂θ of a host computation f(model) for the parameter p: central differences of
    /// the models at its baked value ± h (one-sided at the ends of its valid range).
    template <typename F> std::vector<double> derivative(size_t p, F &&f) const {
        double h = m_params[p].step * std::max(std::abs(m_baked[p]), 1.0);
        std::optional<std::vector<double>> d = fluo_detail::central_difference(h, [&](double delta) {
            std::vector<double> v = m_baked;
            v[p] += delta;
            try {
                rust::Box<fluo::FluoMedium> m = m_build(v);
                return std::optional<std::vector<double>>(f(*m));
            } catch (const std::exception &) {
                return std::optional<std::vector<double>>();
            }
        });
        if (!d)
            Throw("%s: no derivative of the medium in \"%s\" at %g", m_plugin, m_params[p].name, m_baked[p]);
        return *d;
    }

    /// Parameter p's tangent tables, made once per bake.
    const Tangent &tangent(size_t p) const {
        if (!m_tangents[p]) {
            size_t n = m_grid.host.size(), ne = m_egrid.host.size();
            std::vector<double> d = derivative(p, [&](const fluo::FluoMedium &m) {
                fluo::MediumJitTables t = fluo::medium_jit_tables_on(
                    m, rust::Slice<const double>(m_grid.host.data(), n),
                    rust::Slice<const double>(m_egrid.host.data(), ne));
                fluo::Rgb rgb = fluo::medium_absorption_rgb(m);
                std::vector<double> v(t.mu_a.begin(), t.mu_a.end());
                v.insert(v.end(), t.cum.begin(), t.cum.end());
                v.insert(v.end(), t.emission.begin(), t.emission.end());
                v.insert(v.end(), { rgb.r, rgb.g, rgb.b });
                return v;
            });
            auto part = [&](size_t from, size_t count) {
                return fluo_detail::load_floats<FloatStorage>(std::vector<double>(d.begin() + from, d.begin() + from + count));
            };
            bool emits = std::any_of(d.begin() + 2 * n, d.begin() + 2 * n + ne, [](double x) { return x != 0.0; });
            m_tangents[p] = Tangent{ part(0, n), part(n, n), part(2 * n, ne),
                                     { d[2 * n + ne], d[2 * n + ne + 1], d[2 * n + ne + 2] }, emits };
        }
        return *m_tangents[p];
    }

    /// μa's table a lane reads: the baked one, or with the parameters' derivatives.
    const FloatStorage &mu_a_table() const { return m_ad.on ? m_ad.mu_a : m_mu_a; }
    /// C(x) at a host wavelength: the ends of the excitation interval jit_prepare saw as
    /// kernel inputs (an update that bakes other tables keeps the kernel), with the
    /// derivatives where the tables carry them (from the tables).
    Float cum_at(double x) const {
        return x == m_range_at.a ? m_range_at.ca : x == m_range_at.b ? m_range_at.cb : cumulative_at(x, false);
    }
    /// C(x) from the host table (`opaque`: as a kernel input), or from the attached tables.
    Float cumulative_at(double x, bool opaque) const {
        if (!m_ad.on)
            return opaque ? dr::opaque<Float>((float) host_cumulative(x)) : Float((float) host_cumulative(x));
        Float xf = (float) x;
        return cumulative(xf, m_grid.cell(xf, true), true);
    }
    /// The excitation interval of the lights' range [lo, hi] and C at its ends.
    void prepare_range(double lo, double hi) const {
        auto [a, b] = excitation_interval(lo, hi);
        m_range_at = { std::nan(""), std::nan(""), Float(0.f), Float(0.f) };
        if (!(a < b))
            return;
        m_range_at = { a, b, cumulative_at(a, true), cumulative_at(b, true) };
    }

    /// The density times the amount over the baked one.
    Float density(const Interaction3f &mi, const Mask &active) const {
        Float ratio = m_values[0] * m_inv_amount_baked;
        return m_common.density->eval_1(mi, active) * ratio; // (a constant too: traversed, updated)
    }

    Float mu_a_in(const Cell &c, const Mask &active) const {
        const FloatStorage &t = mu_a_table();
        return dr::lerp(fluo_detail::fetch<Float>(t, c.k, active), fluo_detail::fetch<Float>(t, c.k + 1, active), c.f);
    }

    /// μa at the wavelengths (spectral) or its sRGB (RGB), 1/m at density 1.
    UnpolarizedSpectrum absorption(const Wavelength &lambda, const Mask &active) const {
        UnpolarizedSpectrum out(0.f);
        if constexpr (is_spectral_v<Spectrum>) {
            for (size_t j = 0; j < NW; ++j)
                out[j] = mu_a_in(m_grid.cell(lambda[j], active), active);
        } else {
            (void) lambda, (void) active;
            for (size_t j = 0; j < NW && j < 3; ++j)
                out[j] = m_ad.on ? m_ad.rgb[j] : Float((float) m_mu_a_rgb[j]);
        }
        return out;
    }

    /// μ̄: the largest over the wavelengths of (max density · bound + max σs)·scale, at least
    /// the floor, shared by the hero wavelengths (μa varies a hundredfold over the spectrum,
    /// and a per-wavelength majorant would let the first hero wavelength, which samples the
    /// distance, fly through where the others collide, leaving their collisions to rare,
    /// huge weights); in RGB under Mitsuba's interface (`spectrum_bound`) the spectrum's
    /// maximum bounds every channel (fluo_volpath passes its own bound), and the majorant is
    /// NativeMajorantFactor times that: Mitsuba's volpath (also fluo_volpath's path where no
    /// medium fluoresces) draws null or real with one channel's σt/μ̄, so a shared majorant
    /// that this channel's σt reaches (the most absorbing of the hero wavelengths, in a medium
    /// at its largest density) never draws a null collision and the other wavelengths die
    /// at every real one: measured 3.3 % too dark through 2 cm of dots (0.1888 against 0.1952
    /// computed from μa), d/dc 43 % off. With the factor, p_null ≥ 1/2 and a null weight is at
    /// most 2. Detached: it only places tentative collisions.
    UnpolarizedSpectrum majorant(const UnpolarizedSpectrum &bound, const Mask & /* active */,
                                 bool spectrum_bound = true) const {
        UnpolarizedSpectrum m = dr::fmadd(dr::detach(bound), m_maj_density, m_maj_sigma_s) * (float) m_common.scale;
        if constexpr (is_rgb_v<Spectrum>)
            if (spectrum_bound)
                m = dr::maximum(m, UnpolarizedSpectrum(m_maj_rgb));
        Float shared = dr::maximum(dr::max(m), m_maj_floor);
        return UnpolarizedSpectrum(spectrum_bound ? shared * NativeMajorantFactor : shared);
    }

    /// σn = μ̄ − σt, at least 0 in value (rounding) with the derivative −∂σt everywhere: the
    /// majorant bounds σt by construction, and where the most absorbing wavelength sets it
    /// (σn = 0 exactly) a clamp's derivative would be 0, dropping that wavelength's share of
    /// the derivative (measured: AD 0.60-0.88x the image's derivative through a cube of dots).
    static UnpolarizedSpectrum null_rate(const UnpolarizedSpectrum &m_bar, const UnpolarizedSpectrum &sigma_t) {
        UnpolarizedSpectrum n = m_bar - sigma_t;
        return n + dr::detach(dr::maximum(n, 0.f) - n);
    }

    /// [a, b]: the lights' range within the medium's.
    std::pair<double, double> excitation_interval(double lo, double hi) const {
        return { std::max(lo, m_range.lo), std::min(hi, m_range.hi) };
    }

    /// ∫ μa from the grid's start to λ in cell c, nm/m.
    Float cumulative(const Float &lambda, const Cell &c, const Mask &active) const {
        Float x = dr::clip(lambda, c.x0, c.x1);
        Float f0 = fluo_detail::fetch<Float>(mu_a_table(), c.k, active);
        return dr::fmadd(.5f * (x - c.x0), f0 + mu_a_in(c, active),
                         fluo_detail::fetch<Float>(m_ad.on ? m_ad.cum : m_cum, c.k, active));
    }
    double host_cumulative(double lambda) const {
        auto [k, f] = m_grid.host_cell(lambda);
        double x0 = m_grid.host[k], x1 = m_grid.host[k + 1];
        double mu = m_mu_a_host[k] + f * (m_mu_a_host[k + 1] - m_mu_a_host[k]);
        return m_cum_host[k] + .5 * f * (x1 - x0) * (m_mu_a_host[k] + mu);
    }

    /// μf(λo | [a, b]) at density 1, 1/m: e(λo)·(C(min(λo, b)) − C(a))⁺, with c λo's cell.
    Float source(const Float &lambda_o, const Cell &c, double a, double b, const Mask &active) const {
        if (!m_fluorescent || !(a < b))
            return Float(0.f);
        Mask inside = active && lambda_o >= m_egrid.v_l0 && lambda_o <= m_egrid.v_l1;
        Cell ce = m_egrid.cell(lambda_o, inside);
        const FloatStorage &et = m_ad.on ? m_ad.emission : m_emission; // (with the derivatives)
        Float e = dr::lerp(fluo_detail::fetch<Float>(et, ce.k, inside), fluo_detail::fetch<Float>(et, ce.k + 1, inside), ce.f);
        // C(min(λo, b)) from λo's own cell where λo < b
        Float c_top = dr::select(lambda_o < (float) b, cumulative(lambda_o, c, inside), cum_at(b));
        Float mass = c_top - cum_at(a);
        return dr::select(inside && e > 0.f, e * dr::maximum(mass, 0.f), 0.f);
    }

    const char *m_plugin;
    fluo_detail::MediumCommon<Float, Spectrum> m_common;
    std::optional<rust::Box<fluo::FluoMedium>> m_model;
    bool m_fluorescent = false;
    fluo::Range m_range{ 0, 0 };
    std::array<double, 3> m_mu_a_rgb{};
    double m_rgb_mu_max = 0.0;
    double m_mu_max = 0.0; ///< μa's peak, 1/m at density 1 and the baked amount
    /// The model's traversed parameters (the absorber's amount first), their values, on the
    /// host, as the tables were baked (the amount at m_amount_baked), and the Rust model for
    /// other values.
    std::vector<fluo_detail::MediumParam> m_params;
    std::vector<Float> m_values;
    std::vector<double> m_hosts, m_baked;
    double m_amount_baked = 1.0;
    fluo_detail::MediumBuild m_build;
    /// Per parameter, its tangent tables (this bake's, made when a render first wants them).
    mutable std::vector<std::optional<Tangent>> m_tangents;
    /// The tables with the derivatives of the parameters carrying gradients (jit_prepare).
    struct Attached {
        bool on = false;
        FloatStorage mu_a, cum, emission;
        std::array<Float, 3> rgb;
    };
    mutable Attached m_ad;
    /// jit_prepare's excitation interval [a, b] and C at its ends (kernel inputs).
    struct RangeAt {
        double a = std::nan(""), b = std::nan("");
        Float ca, cb;
    };
    mutable RangeAt m_range_at;
    Float m_inv_amount_baked; ///< 1 / m_amount_baked (a kernel input)
    /// The majorant's parts (refresh_majorant): largest density × amount ratio, largest σs
    /// (1/m), floor and RGB bound (inverse scene units), 1/(largest density × ratio × scale).
    Float m_maj_density, m_maj_sigma_s, m_maj_floor, m_maj_rgb, m_inv_rate_unit;
    fluo_detail::UpdateRecord<Float> m_record; ///< the traversed values, as last accepted
    std::string m_what;   ///< what sets μa (the absorption check's message)
    Grid m_grid, m_egrid; ///< μa's nodes, the emission's
    FloatStorage m_mu_a, m_cum, m_emission;
    std::vector<double> m_mu_a_host, m_cum_host;
};

NAMESPACE_END(mitsuba)
