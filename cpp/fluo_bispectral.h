// The bispectral interface that fluo's fluorescent BSDFs implement next to Mitsuba's
// BSDF interface, and that the fluo_path integrator discovers at scene load with
// dynamic_cast (Mitsuba itself is unchanged).
//
// Everything spectral (reradiation values, wavelength sampling and pdfs, excitation
// and emission ranges) is answered by the Rust model behind fluorescence(), through
// the generic fluo_* functions of the bridge (src/bispectral.rs documents them).
// The shim adds only what depends on Mitsuba objects: the elastic albedo, which may
// come from a texture.
#pragma once

#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/interaction.h>

#include "fluo/src/ffi/mod.rs.h"

NAMESPACE_BEGIN(mitsuba)

template <typename Float, typename Spectrum> class BispectralBSDF {
public:
    using SurfaceInteraction3f = SurfaceInteraction<Float, Spectrum>;
    using UnpolarizedSpectrum = unpolarized_spectrum_t<Spectrum>;

    virtual ~BispectralBSDF() = default;

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
