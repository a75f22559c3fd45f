// The bispectral interface that fluo's fluorescent BSDFs implement next to Mitsuba's
// BSDF interface, and that the fluo_path integrator discovers at scene load with
// dynamic_cast (Mitsuba itself is unchanged).
//
// Everything spectral (reradiation values, wavelength sampling and pdfs, excitation
// and emission ranges) is answered by the Rust model behind fluorescence(), through
// the generic fluo_* functions of the bridge (core/src/interface.rs documents them).
// The shim adds only what depends on Mitsuba objects: the elastic albedo, which may
// come from a texture.
#pragma once

#include <array>
#include <atomic>

#include <mitsuba/core/logger.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/interaction.h>

#include "fluo-mitsuba/src/bridge.rs.h"

NAMESPACE_BEGIN(mitsuba)

namespace fluo_detail {
/// Armed when a fluorescent material is constructed (a scene is being loaded),
/// disarmed by the first warning: one "needs fluo_path" warning per loaded scene.
inline std::atomic<bool> &unmanaged_warning_armed() {
    static std::atomic<bool> armed{ true };
    return armed;
}
} // namespace fluo_detail

template <typename Float, typename Spectrum> class BispectralBSDF {
public:
    using SurfaceInteraction3f = SurfaceInteraction<Float, Spectrum>;
    using UnpolarizedSpectrum = unpolarized_spectrum_t<Spectrum>;

    BispectralBSDF() { fluo_detail::unmanaged_warning_armed().store(true, std::memory_order_relaxed); }
    virtual ~BispectralBSDF() = default;

    /// fluo_path marks the materials it transports (wrapped ones included) when it
    /// prepares a render. A fluorescent material sampled by any other integrator
    /// (Mitsuba's path, volpath, direct, ...) renders its elastic part only: it says so
    /// once per loaded scene (warn_if_unmanaged, called from sample()).
    void set_managed(bool managed) const { m_managed.store(managed, std::memory_order_relaxed); }

    /// The fluorescent model, or nullptr when this material never re-emits
    /// (e.g. concentration or quantum yield 0).
    virtual const fluo::Fluorescence *fluorescence() const = 0;

    /// Directional-hemispherical albedo of the elastic part at si.wavelengths, for
    /// light leaving along si.wi. Used only to choose between elastic and shifted
    /// events, so it must be positive wherever the elastic BSDF is.
    virtual UnpolarizedSpectrum elastic_albedo(const SurfaceInteraction3f &si) const = 0;

    /// The elastic part of eval() alone (f·cos θo), without any reradiation. In the
    /// RGB variant eval() serves an equal-energy approximation that includes
    /// fluorescence; reduced transport (fluo_path in scalar_rgb) adds the reradiation
    /// itself as a reduced matrix and needs the elastic part separately.
    virtual UnpolarizedSpectrum eval_elastic(const SurfaceInteraction3f &si,
                                             const Vector<Float, 3> &wo) const = 0;

    // Spatially varying fluorescence (e.g. fluo_jung with a colour texture). The
    // defaults describe a uniform material; a varying one returns its model at si
    // (nullptr where it does not re-emit) and fluorescence() becomes a representative
    // used only to decide that the material fluoresces somewhere.

    /// The fluorescent model at si, or nullptr where the material does not re-emit.
    virtual const fluo::Fluorescence *fluorescence_at(const SurfaceInteraction3f & /* si */) const {
        return fluorescence();
    }

    /// Whether fluorescence_at() depends on si.
    virtual bool fluorescence_varies() const { return false; }

    /// A varying material's fluorescence at si as a mixture of at most MaxMix models
    /// from a finite set (fluorescence_model(index)): f_fl(si) = Σ prob·weight·f_fl[model],
    /// Σ prob = 1. fluo_jung with textured parameters gives one dye shape per (λe, s)
    /// pair scaled by the hit's c·Q (one entry); fluo_qd interpolates models baked on a
    /// (radius, density) grid (up to four entries, bilinear weights as `prob`).
    /// fluo_path picks one entry with probability `prob` in scalar_spectral (an unbiased
    /// estimate of the mixture) and sums the entries' reduced matrices in scalar_rgb.
    struct Local {
        const fluo::Fluorescence *model = nullptr; ///< nullptr: no re-emission from this entry
        size_t index = NoIndex; ///< < fluorescence_models(), or NoIndex
        double weight = 1.0;    ///< scale of the model's reradiation
        double prob = 1.0;      ///< mixture probability
    };
    static constexpr size_t NoIndex = (size_t) -1;
    static constexpr size_t MaxMix = 4;
    using Mixture = std::array<Local, MaxMix>;

    /// The mixture at si: fills `out` and returns its size (default: one entry,
    /// fluorescence_at(si) with weight 1, no index).
    virtual size_t fluorescence_local(const SurfaceInteraction3f &si, Mixture &out) const {
        out[0] = Local{ fluorescence_at(si), NoIndex, 1.0, 1.0 };
        return 1;
    }

    /// Number of models fluorescence_local() indexes (0: it gives no index, and reduced
    /// RGB transport serves the material as a plain BSDF).
    virtual size_t fluorescence_models() const { return 0; }
    /// Model i < fluorescence_models().
    virtual const fluo::Fluorescence *fluorescence_model(size_t /* i */) const { return nullptr; }

protected:
    /// The once-per-scene warning of set_managed(); an atomic load when managed.
    void warn_if_unmanaged(const char *plugin) const {
        if (m_managed.load(std::memory_order_relaxed) || !fluorescence())
            return;
        if (fluo_detail::unmanaged_warning_armed().exchange(false, std::memory_order_relaxed)) {
            constexpr const char *ClassName = "fluo";
            Log(Warn, "%s: this material fluoresces, but the scene's integrator does not transport "
                      "fluorescence: only its elastic (non-shifted) part is rendered (in scalar_rgb an "
                      "equal-energy approximation). Use <integrator type=\"fluo_path\"/> to render "
                      "fluorescence. (This warning is printed once per scene.)", plugin);
        }
    }

private:
    mutable std::atomic<bool> m_managed{ false };
};

/// A texture that knows its emission spectrum (fluo_illuminant), so that reduced
/// transport can use the spectrum's own basis coefficients, including the UV band.
class SpectralSource {
public:
    virtual ~SpectralSource() = default;
    virtual const fluo::Illuminant &illuminant() const = 0;
    /// Luminance of the RGB value the texture evaluates to in scalar_rgb (never 0).
    virtual double rgb_luminance() const = 0;
};

NAMESPACE_END(mitsuba)
