#include <mitsuba/core/fresolver.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/render/texture.h>

#include "fluo_bispectral.h"
#include "fluo_common.h"

NAMESPACE_BEGIN(mitsuba)

/**!

.. _spectrum-fluo_illuminant:

CIE illuminant or measured emission spectrum (:monosp:`fluo_illuminant`)
-----------------------------------------------------------------------

.. pluginparameters::

 * - illuminant
   - |string|
   - A CIE illuminant: ``A``, ``D50``, ``D55``, ``D60``, ``D65``, ``D75``, ``E``,
     ``FL1``–``FL12``, ``HP1``–``HP5`` (case-insensitive). A, E and the D series are
     defined from 300 nm, so they excite fluorescence in the UV; FL and HP from 380 nm.
 * - filename
   - |string|
   - Alternatively, a spectrum as a two-column ``nm,value`` CSV file (``#`` comments
     and one header line allowed), e.g. a UV lamp.
 * - scale
   - |float|
   - Luminance of the result: the spectrum is scaled so that ∫ I ȳ / ∫ ȳ over
     360–830 nm (CIE 1931) equals ``scale``. (Default: 1)
 * - normalize
   - |bool|
   - When false, the values are used as given, times ``scale`` (needed for spectra with
     no visible energy, such as a UV lamp). (Default: true)

Mitsuba's own ``d65`` spectrum and its RGB upsampling stop at 360 nm, where the camera's
wavelength range starts. Fluorescent materials absorb below that, so lights meant to
excite them in ``scalar_spectral`` need a spectrum defined in the UV: this plugin serves
fluo's tabulated CIE illuminants (``data/spectra``, generated from colour-science) or
any tabulated spectrum, linearly interpolated and zero outside its domain. It reports
that domain through ``wavelength_range()``, which ``fluo_path`` uses to decide how far
into the UV excitation can reach. A spectrum that is entirely UV (no luminance) cannot
be luminance-normalised: give ``normalize = false``.

In ``scalar_rgb`` it evaluates to the spectrum's linear sRGB (Mitsuba's conversion; a
negligible grey of 1e-12 for a spectrum without visible energy), and ``fluo_path``'s
reduced transport uses the spectrum's own basis coefficients, UV band included.

.. tabs::
    .. code-tab:: xml

        <emitter type="directional">
            <vector name="direction" value="0, 0, -1"/>
            <spectrum type="fluo_illuminant" name="irradiance">
                <string name="illuminant" value="D65"/>
                <float name="scale" value="3"/>
            </spectrum>
        </emitter>
*/
template <typename Float, typename Spectrum>
class FluoIlluminant final : public Texture<Float, Spectrum>, public SpectralSource {
public:
    MI_IMPORT_TYPES(Texture)

    static constexpr const char *Plugin = "fluo_illuminant";

    FluoIlluminant(const Properties &props) : Texture(props) {
        std::string name = props.has_property("illuminant")
                               ? std::string(props.get<std::string_view>("illuminant")) : "";
        std::string file;
        if (props.has_property("filename")) {
            FileResolver *fr = mitsuba::file_resolver();
            file = fr->resolve(fs::path(std::string(props.get<std::string_view>("filename")))).string();
        }
        double scale = fluo_detail::get_float(Plugin, props, "scale", 1.0);
        bool normalize = props.get<bool>("normalize", true);
        m_spectrum = fluo_detail::rust_call(Plugin, [&] { return fluo::illuminant_new(name, file, scale, normalize); });
        fluo::Range r = fluo::illuminant_range(*m_spectrum);
        m_range = ScalarVector2f((ScalarFloat) r.lo, (ScalarFloat) r.hi);
        m_mean = (ScalarFloat) fluo::illuminant_mean(*m_spectrum);
        fluo::Rgb c = fluo::illuminant_srgb(*m_spectrum);
        m_rgb = Color3f((ScalarFloat) c.r, (ScalarFloat) c.g, (ScalarFloat) c.b);
        // An invisible (e.g. UV-only) spectrum still needs a non-zero RGB, so that
        // reduced transport can recover the emitter's geometric weight from it.
        if (!(dr::mean(m_rgb) > InvisibleRgb))
            m_rgb = Color3f(InvisibleRgb);
    }

    /// RGB reported for spectra without visible energy (negligible, see above).
    static constexpr ScalarFloat InvisibleRgb = 1e-12f;

    UnpolarizedSpectrum eval(const SurfaceInteraction3f &si, Mask /* active */) const override {
        if constexpr (is_spectral_v<Spectrum>) {
            std::array<float, 4> lambda = fluo_detail::wavelengths_of(si.wavelengths), out{};
            fluo::illuminant_eval(*m_spectrum, fluo_detail::slice(lambda), fluo_detail::slice_mut(out));
            return UnpolarizedSpectrum(out[0], out[1], out[2], out[3]);
        } else {
            return m_rgb;
        }
    }

    Float eval_1(const SurfaceInteraction3f &si, Mask active) const override {
        if constexpr (is_spectral_v<Spectrum>)
            return dr::mean(eval(si, active));
        else
            return dr::mean(m_rgb);
    }

    const fluo::Illuminant &illuminant() const override { return *m_spectrum; }
    double rgb_luminance() const override {
        return 0.212671 * m_rgb[0] + 0.715160 * m_rgb[1] + 0.072169 * m_rgb[2];
    }

    Float mean() const override { return m_mean; }
    ScalarVector2f wavelength_range() const override { return m_range; }
    ScalarFloat max() const override {
        return is_spectral_v<Spectrum> ? m_mean * 4.f : dr::max(m_rgb); // only a bound is needed
    }

    std::string to_string() const override {
        return "FluoIlluminant[" + std::string(fluo::illuminant_to_string(*m_spectrum)) + "]";
    }

    MI_DECLARE_CLASS(FluoIlluminant)

private:
    rust::Box<fluo::Illuminant> m_spectrum = fluo_detail::rust_call(
        Plugin, [] { return fluo::illuminant_new("E", "", 1.0, true); });
    ScalarVector2f m_range;
    ScalarFloat m_mean;
    Color3f m_rgb;
};

static const bool fluo_illuminant_registered =
    (fluo_detail::register_scalar_plugin<FluoIlluminant>("fluo_illuminant", ObjectType::Texture), true);

NAMESPACE_END(mitsuba)
