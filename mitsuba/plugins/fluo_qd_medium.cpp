// The fluo_qd_medium plugin: a participating medium of CdSe quantum dots dispersed in a
// host (Benamira & Pattanaik 2023, sec. 4.1). Its documentation is the comment below.
// Physics in Rust (core/src/models/qd/medium.rs, through the bridge's fluo_qd_medium
// section); the Medium and the bispectral medium interface for fluo_volpath are
// include/fluo/fluo_medium.h, shared with fluo_dye_medium.
#include <initializer_list>

#include <type_traits>

#include "fluo_medium.h"

NAMESPACE_BEGIN(mitsuba)

/**!

.. _medium-fluo_qd_medium:

Quantum-dot medium (:monosp:`fluo_qd_medium`)
---------------------------------------------

.. pluginparameters::

 * - radius
   - |float|
   - Dot radius R in nm, [1, 5]. Sets the band edge λQD (Brus equation, eqs. 1-3) and
     the emission peak λQD + Sλ (eq. 6). Traversed and differentiable, as ``width`` and
     ``quantum_yield`` (below). (Default: 2.2)
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
     in 1/m with σ_abs in nm²; μa's peak × ``scale`` × the largest density is at most 1e5
     per scene unit (refused at load beyond: delta tracking would not finish). Traversed: an
     update through ``mi.traverse`` is validated as the load is and scales the tables
     baked at load (μa and the re-emission are linear in it), recompiling nothing;
     differentiable (below). (Default: 1)
 * - density
   - |volume| or |float|
   - Optional spatially varying multiplier of the concentration (a ``gridvolume``, as
     ``heterogeneous``'s ``sigma_t``): the medium is then bounded by the grid's box and
     rendered by delta tracking against the grid's maximum. Without it (or with a float,
     a constant multiplier) the medium is homogeneous and unbounded (bounded by its shape,
     as ``homogeneous``).
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

**Rendering.** With ``fluo_volpath`` in the spectral variants the medium fluoresces by
wavelength shifting (the integrator's docs have the estimator). In every variant the
medium interpolates Rust's tables: μa linear between the model's own table nodes,
exactly as above, extended at 0.5 nm steps to 200-1200 nm (within 5e-5 of its peak),
and the emission line between nodes that hold it within 1e-5 of its peak. Mitsuba's own
``volpath`` (and any other integrator) renders it as an absorbing, scattering medium
without re-emission — exactly its Q = 0 limit — and warns once per scene when Q > 0. In
the RGB variants the absorption other integrators see is μa's linear sRGB as Mitsuba
converts any spectrum (CIE 1931, white = 1; negative channels clipped to 0);
``fluo_volpath`` in the RGB variants carries the medium's reduced operators instead (its
docs).

**Updates and gradients.** ``radius``, ``width`` and ``quantum_yield`` are traversed: an
update is validated as the load is and bakes the tables again, as a rule into the same
kernels (the tables and what they fix are kernel inputs; measured: radius updates from 2.2
to 3.1 compile nothing; a node count crossing a power of two, or a grid whose narrowest
cell changes its lookup, compiles another). Every traversed parameter (those three, ``concentration``,
``density`` as a float's value or a grid's voxels, and ``sigma_s``) is differentiable
through ``fluo_volpath`` in ``llvm_ad_spectral`` and ``llvm_ad_rgb`` (and the cuda ones):
its tracking weighs each null or real event by the medium's rate there over a detached
probability under a detached majorant, so AD differentiates the integrand and not the
sampling (the fluorescent events as their chosen branch's rate, a shift also by the
excitation density at its λi; in RGB the reduced operators scale with the density). For
the radius, width and yield, when a render finds them carrying gradients the medium
bakes Rust's tables at θ ± h on its own nodes (h = 1e-3·max(θ, 1), one-sided at the ends
of the range) and reads value + (θ − detach(θ))·∂/∂θ from those differences (the same
values); in RGB the reduced operators carry the differences of Rust's reductions the same
way. The derivative in the yield at Q = 0 is refused with an error (nothing re-emits, so
no re-emission is sampled to carry it): differentiate from Q > 0. A scene whose media do
not fluoresce renders with ``volpath`` and differentiates with this loop.

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
/// A fluo_qd_medium's configuration from its properties (every variant).
inline fluo::QdMediumConfig qd_medium_config(const Properties &props, const char *plugin) {
    fluo::QdMediumConfig c = fluo::qd_medium_default_config(); // the defaults live in Rust
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
        *field = fluo_detail::get_float<double>(plugin, props, name, *field);
    return c;
}

/// The plugin over Rust's tables (FluoMediumBase, fluo_medium.h), in every variant.
template <typename Float, typename Spectrum> class FluoQdMedium final : public FluoMediumBase<Float, Spectrum> {
public:
    using Base = FluoMediumBase<Float, Spectrum>;

    static constexpr const char *Plugin = "fluo_qd_medium";

    FluoQdMedium(const Properties &props) : Base(props, Plugin) {
        fluo::QdMediumConfig c = qd_medium_config(props, Plugin);
        using C = fluo::QdMediumConfig;
        this->init({ { "concentration", c.concentration, 0.0 }, { "radius", c.radius, 1e-3 },
                     { "width", c.width, 1e-3 }, { "quantum_yield", c.quantum_yield, 1e-3 } },
                   fluo_detail::medium_builder(Plugin, c,
                                               { &C::concentration, &C::radius, &C::width, &C::quantum_yield },
                                               [](const C &at) { return fluo::qd_medium_new(at); }),
                   "the dots' concentration and radius");
    }

    std::string to_string() const override { return this->describe("FluoQdMedium"); }

    MI_DECLARE_CLASS(FluoQdMedium)
};

static const bool fluo_qd_medium_registered =
    (fluo_detail::register_plugin<FluoQdMedium>("fluo_qd_medium", ObjectType::Medium), true);

NAMESPACE_END(mitsuba)
