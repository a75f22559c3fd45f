// The fluo_dye_medium plugin: a fluorescent dye dissolved in a participating medium,
// with Jung et al.'s absorption and emission spectra. Its documentation is the comment
// below. Physics in Rust (DyeMedium in core/src/models/jung.rs); the Medium and the bispectral
// medium interface for fluo_volpath are include/fluo/fluo_medium.h.
#include <initializer_list>

#include <type_traits>

#include "fluo_medium.h"

NAMESPACE_BEGIN(mitsuba)

/**!

.. _medium-fluo_dye_medium:

Fluorescent dye medium (:monosp:`fluo_dye_medium`)
--------------------------------------------------

.. pluginparameters::

 * - emission_peak
   - |float|
   - Emission peak λe in nm, [200, 1200]. (Default: 520)
 * - stokes_shift
   - |float|
   - Distance between the emission and absorption peaks in nm, in (0, s_max(λe)] as for
     ``fluo_jung``. (Default: 60)
 * - quantum_yield
   - |float|
   - Quantum yield Q in [0, 1]. 0: an absorbing, non-fluorescent medium. (Default: 0.9)
 * - sigma_a
   - |float|
   - Peak absorption coefficient in 1/m, [0, 1e9]; with ``scale`` and the largest density,
     at most 1e5 per scene unit (refused at load beyond: tracking would not finish).
     Traversed, updated as ``fluo_qd_medium``'s concentration (the tables scaled, not
     re-baked; differentiable through ``fluo_volpath``, as ``fluo_qd_medium``'s). (Default: 100)
 * - density, sigma_s, (phase function), scale
   - 
   - As for ``fluo_qd_medium``: an optional density grid multiplying the dye, the host's
     elastic scattering (1/m) and its phase function, metres per scene unit.

``emission_peak``, ``stokes_shift`` and ``quantum_yield`` are traversed (an update bakes the
tables again) and differentiable through ``fluo_volpath`` in both AD variants, with the
tangent tables ``fluo_qd_medium`` describes (h: 1e-4·λe, 1e-3·s, 1e-3).

A dye in solution, with the spectra of Jung et al. (2018, 2019; eqs. 3-6 of the 2019
paper): a cubic b-spline emission e(λ) of unit integral around λe and its mirrored
absorption a(λ) ∈ [0, 1] peaking at λe − s. μa(λ) = σa a(λ); an absorbed photon is
re-emitted isotropically with probability Q at λo ~ e (the supports never overlap, so
always at a longer wavelength). With ``fluo_volpath`` in every variant (spectral: by
wavelength shifting; RGB: reduced transport) the dye fluoresces (as ``fluo_qd_medium``:
both implement fluo's bispectral medium interface; in every variant μa is linear between
4096 nodes across the absorption band, within 3e-7 of its peak, and e between nodes
within 1e-5 of its peak); elsewhere it absorbs only (native ``volpath`` warns once per
scene).

.. tabs::
    .. code-tab:: xml

        <medium type="fluo_dye_medium" id="fluorescein">
            <float name="emission_peak" value="515"/>
            <float name="stokes_shift" value="25"/>
            <float name="sigma_a" value="200"/>
            <float name="scale" value="0.01"/>
        </medium>
*/

/// Over Rust's tables (FluoMediumBase, fluo_medium.h), as fluo_qd_medium.
template <typename Float, typename Spectrum> class FluoDyeMedium final : public FluoMediumBase<Float, Spectrum> {
public:
    using Base = FluoMediumBase<Float, Spectrum>;

    static constexpr const char *Plugin = "fluo_dye_medium";

    FluoDyeMedium(const Properties &props) : Base(props, Plugin) {
        fluo::DyeMediumConfig c = fluo::dye_medium_default_config(); // the defaults live in Rust
        for (auto [name, field] : std::initializer_list<std::pair<const char *, double *>>{
                 { "emission_peak", &c.emission_peak }, { "stokes_shift", &c.stokes_shift },
                 { "quantum_yield", &c.quantum_yield }, { "sigma_a", &c.sigma_a } })
            *field = fluo_detail::get_float<double>(Plugin, props, name, *field);
        using C = fluo::DyeMediumConfig;
        this->init({ { "sigma_a", c.sigma_a, 0.0 }, { "emission_peak", c.emission_peak, 1e-4 },
                     { "stokes_shift", c.stokes_shift, 1e-3 }, { "quantum_yield", c.quantum_yield, 1e-3 } },
                   fluo_detail::medium_builder(Plugin, c,
                                               { &C::sigma_a, &C::emission_peak, &C::stokes_shift, &C::quantum_yield },
                                               [](const C &at) { return fluo::dye_medium_new(at); }),
                   "sigma_a");
    }

    std::string to_string() const override { return this->describe("FluoDyeMedium"); }

    MI_DECLARE_CLASS(FluoDyeMedium)
};

static const bool fluo_dye_medium_registered =
    (fluo_detail::register_plugin<FluoDyeMedium>("fluo_dye_medium", ObjectType::Medium), true);

NAMESPACE_END(mitsuba)
