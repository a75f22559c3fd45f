// The fluo_qd_medium plugin: a participating medium of CdSe quantum dots dispersed in a
// host (Benamira & Pattanaik 2023, sec. 4.1). Its documentation is the comment below.
// Physics in Rust (core/src/models/qd/medium.rs, through the bridge's fluo_qd_medium
// section); this shim is Mitsuba's Medium interface plus fluo's bispectral medium
// interface (include/fluo/fluo_bispectral_medium.h) for fluo_volpath.
#include <mitsuba/core/properties.h>
#include <mitsuba/render/medium.h>
#include <mitsuba/render/phase.h>
#include <mitsuba/render/volume.h>

#include <array>
#include <cmath>
#include <initializer_list>
#include <optional>
#include <sstream>

#include "fluo_bispectral_medium.h"
#include "fluo_common.h"

NAMESPACE_BEGIN(mitsuba)

/**!

.. _medium-fluo_qd_medium:

Quantum-dot medium (:monosp:`fluo_qd_medium`)
---------------------------------------------

.. pluginparameters::

 * - radius
   - |float|
   - Dot radius R in nm, [1, 5]. Sets the band edge λQD (Brus equation, eqs. 1-3) and
     the emission peak λQD + Sλ (eq. 6). (Default: 2.2)
 * - width
   - |float|
   - Width δλ of the absorption and emission bands in nm, [0.01, 100]. (Default: 15)
 * - quantum_yield
   - |float|
   - Quantum yield Q in [0, 1]: the fraction of absorbed power re-emitted. 0 gives an
     absorbing, non-fluorescent medium (what native ``volpath`` renders). (Default: 0.8)
 * - concentration
   - |float|
   - Molar concentration of dots in µmol/L, [0, 1e6]. μa(λ) = c · σ_abs(λ) · N_A·10⁻²¹
     in 1/m with σ_abs in nm². (Default: 1)
 * - density
   - |volume|
   - Optional spatially varying multiplier of the concentration (a ``gridvolume``, as
     ``heterogeneous``'s ``sigma_t``): the medium is then bounded by the grid's box and
     rendered by delta tracking against the grid's maximum. Without it the medium is
     homogeneous and unbounded (bounded by its shape, as ``homogeneous``).
 * - sigma_s
   - |spectrum| or |volume|
   - Elastic scattering coefficient of the host in 1/m, ≥ 0 (the dots' own Rayleigh
     scattering is negligible, sec. 4.1). (Default: 0)
 * - (phase function)
   - |phase|
   - Phase function of the host's scattering, any Mitsuba phase plugin. (Default:
     ``isotropic``). Fluorescent re-emission is always isotropic.
 * - scale
   - |float|
   - Length of one scene unit in metres: every coefficient (given per metre) is
     multiplied by it, > 0. E.g. 0.01 for a scene modelled in cm. (Default: 1)
 * - ext_ior
   - |float|
   - Refractive index of the host, [1, 3] (it enters the cross sections, eq. 7; the
     boundary's refraction is the enclosing shape's BSDF). (Default: 1.446, chloroform)
 * - lambda_min, lambda_max
   - |float|
   - Range of the emission normalisation (eqs. 11-15) in nm, 200 ≤ min < max ≤ 1200:
     absorption outside it is not re-emitted. (Default: 300, 830)
 * - table_step
   - |float|
   - Base λ step of the absorption table in nm, [0.05, 50] (refined to δλ/8 around λQD).
     (Default: 1)
 * - gap_energy, ..., temperature
   - |float|
   - The paper's Table 1 constants (SI units), as for ``fluo_qd``. (Default: CdSe)

**Physics.** Dots of radius R absorb with the cross section of eq. 9: Rayleigh
absorption of the dot's bulk below λQD (eq. 7, with the local field factor; our
reading of eq. 7 is documented in core/src/models/qd/index.rs) plus a Gaussian quantum
absorption around λQD, continuous at λQD. An absorbed photon is re-emitted
isotropically with probability Q at a wavelength λo > λi drawn from the logistic
emission line centred at λQD + Sλ (eq. 10), normalised over [λmin, λmax] (eqs. 13, 15):
per unit absorbed power at λi the medium re-emits f(λi → λo) = Q L(λo)/I per nm, never
more than Q in total (no anti-Stokes emission: the part of the line below λi is not
emitted). The absorption coefficient is tabulated once (exact at the nodes,
piecewise linear between them, within 0.5 % of the formula); that table is the
medium's absorption everywhere, including fluo_volpath's excitation sampling, which
inverts its CDF exactly.

**Rendering.** With ``fluo_volpath`` in ``scalar_spectral`` the medium fluoresces (the
integrator's docs have the estimator). Mitsuba's own ``volpath`` (and any other
integrator) renders it as an absorbing, scattering medium without re-emission — exactly
its Q = 0 limit — and warns once per scene when Q > 0. In ``scalar_rgb`` the absorption
is μa's linear sRGB as Mitsuba converts any spectrum (CIE 1931, white = 1; negative
channels clipped to 0), elastic only: ``fluo_volpath`` refuses a fluorescent medium in
``scalar_rgb`` (no reduced transport for media yet) rather than render it without its
glow.

.. tabs::
    .. code-tab:: xml

        <medium type="fluo_qd_medium" id="dots">
            <float name="radius" value="2.7"/>
            <float name="concentration" value="2"/>
            <float name="quantum_yield" value="0.8"/>
            <float name="scale" value="0.01"/>  <!-- scene in cm -->
            <phase type="isotropic"/>
        </medium>
        <shape type="cube">
            <bsdf type="dielectric"><float name="int_ior" value="1.446"/></bsdf>
            <ref name="interior" id="dots"/>
        </shape>
*/
template <typename Float, typename Spectrum>
class FluoQdMedium final : public Medium<Float, Spectrum>, public BispectralMedium<Float, Spectrum> {
public:
    MI_IMPORT_BASE(Medium, m_is_homogeneous, m_has_spectral_extinction, m_phase_function)
    MI_IMPORT_TYPES(Scene, Sampler, Texture, Volume)

    static constexpr const char *Plugin = "fluo_qd_medium";
    /// The majorant's floor relative to its largest value over the spectrum: null
    /// collisions where the medium is (nearly) transparent, at most one per 10⁶ mean
    /// free paths of its most opaque wavelength.
    static constexpr double MajorantFloor = 1e-6;
    /// Absolute floor (a medium with no dots and no scattering), inverse scene units.
    static constexpr double MinMajorant = 1e-30;

    FluoQdMedium(const Properties &props) : Base(props) {
        fluo::QdMediumConfig &c = m_config; // the defaults live in Rust (QdMediumParams)
        fluo::QdConstants &k = c.constants;
        for (auto [name, field] : std::initializer_list<std::pair<const char *, double *>>{
                 { "radius", &c.radius }, { "width", &c.width }, { "quantum_yield", &c.quantum_yield },
                 { "concentration", &c.concentration }, { "ext_ior", &c.ext_ior },
                 { "lambda_min", &c.lambda_min }, { "lambda_max", &c.lambda_max }, { "table_step", &c.table_step },
                 { "gap_energy", &k.gap_energy }, { "elementary_charge", &k.elementary_charge },
                 { "planck", &k.planck }, { "light_speed", &k.light_speed }, { "boltzmann", &k.boltzmann },
                 { "electron_mass", &k.electron_mass }, { "hole_mass", &k.hole_mass },
                 { "vacuum_permittivity", &k.vacuum_permittivity },
                 { "relative_permittivity", &k.relative_permittivity }, { "temperature", &k.temperature } })
            *field = get_double(props, name, *field);
        m_scale = get_double(props, "scale", 1.0);
        if (!(m_scale > 0.0) || !std::isfinite(m_scale))
            Throw("%s: invalid parameter \"scale\" = %g: valid range is (0, inf) (metres per scene unit)",
                  Plugin, m_scale);

        // Never "homogeneous" to Mitsuba, even without a grid: volpath then clips the ray
        // at each tentative collision (ray.maxt = t), which is exact only without null
        // collisions, and this medium has them (its majorant is shared by the hero
        // wavelengths). m_bounded: whether the density grid bounds it.
        m_bounded = props.has_property("density");
        m_is_homogeneous = false;
        m_density = props.get_volume<Volume>("density", 1.f);
        m_max_density = (double) m_density->max();
        if (!(m_max_density >= 0.0) || !std::isfinite(m_max_density))
            Throw("%s: invalid parameter \"density\": its maximum %g must be finite and >= 0", Plugin,
                  m_max_density);
        m_sigma_s = props.get_volume<Volume>("sigma_s", 0.f);
        m_max_sigma_s = (double) m_sigma_s->max();
        if (!(m_max_sigma_s >= 0.0) || !std::isfinite(m_max_sigma_s))
            Throw("%s: invalid parameter \"sigma_s\": its maximum %g must be finite and >= 0", Plugin,
                  m_max_sigma_s);
        m_has_spectral_extinction = true;

        m_model = fluo_detail::rust_call(Plugin, [&] { return fluo::qd_medium_new(m_config); });
        m_fluorescent = fluo::qd_medium_is_fluorescent(**m_model);
        m_range = fluo::qd_medium_lambda_range(**m_model);
        fluo::Rgb a = fluo::qd_medium_absorption_rgb(**m_model);
        m_mu_a_rgb = { a.r, a.g, a.b };
        // The majorant's floor: where μa and σs vanish (beyond the band edge) σt = 0, and
        // volpath's mean null probability σn/μ̄ would be 0/0 (NaN) without it.
        double mu_max = 0.0;
        std::array<float, 4> lambda{}, mu{};
        for (int l = 200; l <= 1200; l += 4) {
            for (size_t j = 0; j < 4; ++j)
                lambda[j] = (float) (l + j);
            fluo::qd_medium_absorption(**m_model, fluo_detail::slice(lambda), fluo_detail::slice_mut(mu));
            for (float v : mu)
                mu_max = std::max(mu_max, (double) v);
        }
        m_majorant_floor = std::max(MajorantFloor * (mu_max * m_max_density + m_max_sigma_s) * m_scale, MinMajorant);
    }

    void traverse(TraversalCallback *cb) override {
        cb->put("density", m_density, ParamFlags::NonDifferentiable);
        cb->put("sigma_s", m_sigma_s, ParamFlags::NonDifferentiable);
        Base::traverse(cb);
    }

    std::tuple<Mask, Float, Float> intersect_aabb(const Ray3f &ray) const override {
        if (!m_bounded)
            return { true, 0.f, dr::Infinity<Float> };
        return m_density->bbox().ray_intersect(ray);
    }

    UnpolarizedSpectrum get_majorant(const MediumInteraction3f &mi, Mask active) const override {
        DRJIT_MARK_USED(active);
        return majorant(absorption(mi));
    }

    std::tuple<UnpolarizedSpectrum, UnpolarizedSpectrum, UnpolarizedSpectrum>
    get_scattering_coefficients(const MediumInteraction3f &mi, Mask active) const override {
        this->warn_if_unmanaged(Plugin);
        Float d = m_bounded ? m_density->eval_1(mi, active) : Float(1.f);
        UnpolarizedSpectrum mu_a = absorption(mi);
        UnpolarizedSpectrum sigma_s = m_sigma_s->eval(mi, active) * (Float) m_scale;
        UnpolarizedSpectrum sigma_t = mu_a * d * (Float) m_scale + sigma_s;
        UnpolarizedSpectrum sigma_n = dr::maximum(majorant(mu_a) - sigma_t, 0.f);
        return { sigma_s, sigma_n, sigma_t };
    }

    // ------------------------------------------------- the bispectral interface

    bool fluorescent() const override { return m_fluorescent; }
    fluo::Range lambda_range() const override { return m_range; }

    void shift_coefficients(const MediumInteraction3f &mei, const fluo::Range &range,
                            std::array<float, 4> &out) const override {
        out.fill(0.f);
        if constexpr (is_spectral_v<Spectrum>) {
            double d = m_bounded ? (double) m_density->eval_1(mei, true) : 1.0;
            if (!(d > 0.0))
                return;
            std::array<float, 4> lambda = fluo_detail::wavelengths_of(mei.wavelengths);
            fluo::qd_medium_shift_coefficients(**m_model, fluo_detail::slice(lambda), range,
                                               fluo_detail::slice_mut(out));
            for (float &v : out)
                v = (float) (v * d * m_scale);
        }
    }

    fluo::Sample sample_excitation(double lambda_o, double xi, const fluo::Range &range) const override {
        return fluo::qd_medium_sample_excitation(**m_model, lambda_o, xi, range);
    }

    std::string to_string() const override {
        std::ostringstream oss;
        oss << "FluoQdMedium[" << std::endl
            << "  model = " << std::string(fluo::qd_medium_to_string(**m_model)) << "," << std::endl
            << "  scale = " << m_scale << "," << std::endl
            << "  density_grid = " << m_bounded << "," << std::endl
            << "  density = " << string::indent(m_density) << "," << std::endl
            << "  sigma_s = " << string::indent(m_sigma_s) << "," << std::endl
            << "  phase_function = " << string::indent(m_phase_function) << std::endl
            << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(FluoQdMedium)

private:
    static double get_double(const Properties &props, const char *name, double def) {
        if (!props.has_property(name))
            return def;
        try {
            return props.get<double>(name);
        } catch (const std::exception &e) {
            Throw("%s: parameter \"%s\" must be a number (%s)", Plugin, name, e.what());
        }
    }

    /// μ̄ = max over the hero wavelengths of (max density · μa + max σs) · scale, at least
    /// the floor (inverse scene units), the same for every wavelength: μa varies a
    /// hundredfold over the spectrum, and a per-wavelength majorant would let the first
    /// hero wavelength (which samples the distance) fly through where the others collide,
    /// leaving their collisions (and fluorescence) to rare, huge weights.
    UnpolarizedSpectrum majorant(const UnpolarizedSpectrum &mu_a) const {
        UnpolarizedSpectrum m = (mu_a * (Float) m_max_density + (Float) m_max_sigma_s) * (Float) m_scale;
        return UnpolarizedSpectrum(dr::maximum(dr::max(m), (Float) m_majorant_floor));
    }

    /// μa at the interaction's wavelengths (spectral) or its sRGB (RGB), 1/m, density 1.
    UnpolarizedSpectrum absorption(const MediumInteraction3f &mi) const {
        UnpolarizedSpectrum out(0.f);
        if constexpr (is_spectral_v<Spectrum>) {
            std::array<float, 4> lambda = fluo_detail::wavelengths_of(mi.wavelengths), mu{};
            fluo::qd_medium_absorption(**m_model, fluo_detail::slice(lambda), fluo_detail::slice_mut(mu));
            for (size_t j = 0; j < dr::size_v<UnpolarizedSpectrum>; ++j)
                out[j] = mu[j];
        } else {
            for (size_t j = 0; j < dr::size_v<UnpolarizedSpectrum> && j < 3; ++j)
                out[j] = (float) m_mu_a_rgb[j];
        }
        return out;
    }

    fluo::QdMediumConfig m_config = fluo::qd_medium_default_config();
    std::optional<rust::Box<fluo::QdMediumModel>> m_model;
    ref<Volume> m_density, m_sigma_s;
    /// Metres per scene unit; the density's and σs's maxima (the majorant's parts).
    double m_scale = 1.0, m_max_density = 1.0, m_max_sigma_s = 0.0, m_majorant_floor = MinMajorant;
    bool m_fluorescent = false;
    bool m_bounded = false;
    fluo::Range m_range{ 0, 0 };
    std::array<double, 3> m_mu_a_rgb{};
};

static const bool fluo_qd_medium_registered =
    (fluo_detail::register_scalar_plugin<FluoQdMedium>("fluo_qd_medium", ObjectType::Medium), true);

NAMESPACE_END(mitsuba)
