// The bispectral interface of fluo's fluorescent participating media, next to
// Mitsuba's Medium interface, which the fluo_volpath integrator discovers at render
// start with dynamic_cast (Mitsuba itself is unchanged). Any volumetric fluorophore
// (fluo_qd_medium, fluo_dye_medium: both through FluoMediumShim) plugs into
// fluo_volpath through it:
//
//   absorption μa(x, λ)            part of the Medium's σt (Mitsuba's interface)
//   μf(x, λo | R) and λi           shift_and_sample(): the source coefficient a camera
//                                  path at λo sees from excitations λi in R,
//                                  ∫_R μa(x, λi) f(λi → λo) dλi (f: re-emitted power per
//                                  nm of λo per unit absorbed power at λi, ∫ f dλo ≤ yield),
//                                  with λi ~ p = μa f / μf exactly, so that a shift's
//                                  weight is μf (the medium must guarantee this)
//   μf(x, λo | all)                source_bound(): a bound for any R, at every collision
//   [λmin, λmax]                   lambda_range(): where it absorbs-to-re-emit and emits
//   A, F, density                  reduced_operators(), density_at(): scalar_rgb
//
// Re-emission is isotropic. The medium's σs is its elastic scattering only; its
// absorption is all of σa (fluorescent or not), so σt = σa + σs and the fluorescent
// source is an extra "scattering" coefficient μf that fluo_volpath adds at real
// collisions (its docs have the estimator).
#pragma once

#include <array>
#include <atomic>
#include <cmath>

#include <mitsuba/core/logger.h>
#include <mitsuba/render/interaction.h>

#include "fluo-mitsuba/src/bridge.rs.h"

NAMESPACE_BEGIN(mitsuba)

namespace fluo_detail {
/// Isotropic re-emission, 1/(4π) per steradian (fluo_volpath, every variant).
constexpr float InvFourPi = (float) (0.25 * M_1_PI);

/// Armed when a fluorescent medium is constructed, disarmed by the first warning:
/// one "needs fluo_volpath" warning per loaded scene.
inline std::atomic<bool> &unmanaged_medium_warning_armed() {
    static std::atomic<bool> armed{ true };
    return armed;
}

/// fluo_volpath's request for the next free flight in a fluorescent medium, per thread
/// (inverse scene units, 0: none): its majorant should also cover the fluorescent
/// source up to this rate, so that tentative collisions happen where the medium
/// re-emits at a path's wavelengths even where it does not absorb them (set around one
/// Medium::sample_interaction call, whose get_majorant and get_scattering_coefficients
/// both read it).
inline double &source_rate_request() {
    thread_local double rate = 0.0;
    return rate;
}
struct ScopedSourceRate {
    explicit ScopedSourceRate(double rate) { source_rate_request() = rate; }
    ~ScopedSourceRate() { source_rate_request() = 0.0; }
    ScopedSourceRate(const ScopedSourceRate &) = delete;
    ScopedSourceRate &operator=(const ScopedSourceRate &) = delete;
};
} // namespace fluo_detail

/// What every fluorescent medium shares in every variant: whether fluo_volpath transports
/// its fluorescence this render, and the once-per-scene warning when no integrator does.
class ManagedMedium {
public:
    ManagedMedium() { fluo_detail::unmanaged_medium_warning_armed().store(true, std::memory_order_relaxed); }
    virtual ~ManagedMedium() = default;

    /// fluo_volpath marks the media it transports when it prepares a render; any other
    /// integrator renders absorption without re-emission and says so once per scene.
    void set_managed(bool managed) const { m_managed.store(managed, std::memory_order_relaxed); }

protected:
    /// Warn (once per scene) when `fluorescent` and no fluo_volpath manages the medium.
    void warn_if_unmanaged(const char *plugin, bool fluorescent) const {
        if (m_managed.load(std::memory_order_relaxed) || !fluorescent)
            return;
        if (fluo_detail::unmanaged_medium_warning_armed().exchange(false, std::memory_order_relaxed)) {
            constexpr const char *ClassName = "fluo";
            Log(Warn, "%s: this medium fluoresces, but the scene's integrator does not transport "
                      "fluorescence in media: it absorbs without re-emitting. Use "
                      "<integrator type=\"fluo_volpath\"/> to render its fluorescence. (This warning is printed once per scene.)",
                plugin);
        }
    }

private:
    mutable std::atomic<bool> m_managed{ false };
};

template <typename Float, typename Spectrum> class BispectralMedium : public ManagedMedium {
public:
    using MediumInteraction3f = MediumInteraction<Float, Spectrum>;

    virtual ~BispectralMedium() = default;

    /// Whether the medium ever re-emits (yield > 0, fluorophores present).
    virtual bool fluorescent() const = 0;

    /// [λmin, λmax], nm: absorption outside it is not re-emitted, emission lies inside.
    virtual fluo::Range lambda_range() const = 0;

    /// For each of mei's wavelengths λo_j: mu_f[j] = μf(x, λo_j | R) in inverse scene
    /// units at mei.p (density and scale included), and samples[j] = λi ~ μa(λi)
    /// f(λi → λo_j) / μf over R drawn with xi[j] (pdf 0 where μf = 0; the density does
    /// not depend on x: a density grid scales μa uniformly in λ). A fluorescent
    /// collision's questions, in one call.
    virtual void shift_and_sample(const MediumInteraction3f &mei, const fluo::Range &range,
                                  const std::array<double, 4> &xi, std::array<float, 4> &mu_f,
                                  std::array<fluo::Sample, 4> &samples) const = 0;

    /// An upper bound of shift_and_sample's μf for any R (μf over the medium's whole
    /// range), cheap at every tentative collision (fluo_volpath's collision probabilities).
    virtual void source_bound(const MediumInteraction3f &mei, std::array<float, 4> &out) const = 0;

    /// scalar_rgb (fluo_volpath's reduced transport): the medium's absorption A and
    /// reradiation F reduced for the transport `t` (fluo::medium_reduced), K×K row major
    /// each, per scene unit at density 1: μa(x) acts on basis coefficients as
    /// density_at(x)·A, and light c re-emits density_at(x)·F·c/(4π) per steradian.
    virtual void reduced_operators(const fluo::TransportBasis &t, rust::Slice<double> a,
                                   rust::Slice<double> f) const = 0;

    /// Whether the medium's extinction is the same everywhere (no density grid, a
    /// constant σs); then `sigma_t` receives it at mei's wavelengths, inverse scene units
    /// (fluo_volpath's shadow rays take its transmittance in closed form).
    virtual bool constant_extinction(const MediumInteraction3f &mei,
                                     typename MediumInteraction3f::UnpolarizedSpectrum &sigma_t) const = 0;

    /// The density at mei.p, 1 without a density grid.
    virtual Float density_at(const MediumInteraction3f &mei) const = 0;

    /// scalar_rgb: the largest diagonal entry of the reduced absorption operator A of the
    /// transport fluo_volpath prepared (per scene unit, density 1; 0: none). The RGB
    /// majorant then bounds the bands it transports, not the whole spectrum (a narrower
    /// majorant, fewer null collisions; the tracking's weights are exact either way).
    void set_band_absorption_max(double a) const { m_band_mu_a_max.store(a, std::memory_order_relaxed); }

protected:
    void warn_if_unmanaged(const char *plugin) const { ManagedMedium::warn_if_unmanaged(plugin, fluorescent()); }

    double band_absorption_max() const { return m_band_mu_a_max.load(std::memory_order_relaxed); }

private:
    mutable std::atomic<double> m_band_mu_a_max{ 0.0 };
};

NAMESPACE_END(mitsuba)
