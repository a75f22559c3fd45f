#include <algorithm>
#include <mitsuba/core/fresolver.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/render/texture.h>

#include <cmath>
#include <sstream>

#include "fluo_common.h"
#include "fluo_bispectral.h"

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
excite them in the spectral variants need a spectrum defined in the UV: this plugin serves
fluo's tabulated CIE illuminants (``data/spectra``, generated from colour-science) or
any tabulated spectrum, linearly interpolated and zero outside its domain. It reports
that domain through ``wavelength_range()``, which ``fluo_path`` uses to decide how far
into the UV excitation can reach. A spectrum that is entirely UV (no luminance) cannot
be luminance-normalised: give ``normalize = false``.

In the RGB variants it evaluates to the spectrum's linear sRGB (Mitsuba's conversion; a
negligible grey of 1e-12 for a spectrum without visible energy), and ``fluo_path``'s
reduced transport uses the spectrum's own basis coefficients, UV band included. In the
spectral variants it is evaluated per lane as Mitsuba's own ``regular``/``irregular``
spectrum through the same nodes (should Mitsuba refuse that table, ``scalar_spectral``
asks Rust per sample and the llvm/cuda variants raise an error).

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

    FluoIlluminant(const Properties &props) : Texture(props), m_spectrum(create(props)) {
        if constexpr (is_spectral_v<Spectrum>) {
            m_table = native_table(*m_spectrum);
            if (!m_table)
                Throw("%s: Mitsuba refused the spectrum's table (%s), which this variant needs",
                      Plugin, std::string(fluo::illuminant_to_string(*m_spectrum)));
        }
        fluo::Range r = fluo::illuminant_range(*m_spectrum);
        m_range = ScalarVector2f((ScalarFloat) r.lo, (ScalarFloat) r.hi);
        m_mean = (ScalarFloat) fluo::illuminant_mean(*m_spectrum);
        fluo::Rgb c = fluo::illuminant_srgb(*m_spectrum);
        m_rgb_host = ScalarColor3f((ScalarFloat) c.r, (ScalarFloat) c.g, (ScalarFloat) c.b);
        // An invisible (e.g. UV-only) spectrum still needs a non-zero RGB, so that
        // reduced transport can recover the emitter's geometric weight from it.
        if (!(dr::mean(m_rgb_host) > InvisibleRgb))
            m_rgb_host = ScalarColor3f(dark(*m_spectrum) ? 0.f : InvisibleRgb);
        m_rgb = Color3f(m_rgb_host);
    }

    /// RGB reported for spectra without visible energy (negligible, see above).
    static constexpr ScalarFloat InvisibleRgb = 1e-12f;

    UnpolarizedSpectrum eval(const SurfaceInteraction3f &si, Mask active) const override {
        if constexpr (is_spectral_v<Spectrum>) {
            return m_table->eval(si, active); // the constructor ensured it exists
        } else {
            return m_rgb;
        }
    }

    Float eval_1(const SurfaceInteraction3f &si, Mask active) const override {
        return dr::mean(eval(si, active));
    }

    const fluo::Illuminant &illuminant() const override { return *m_spectrum; }
    double rgb_luminance() const override {
        return 0.212671 * m_rgb_host[0] + 0.715160 * m_rgb_host[1] + 0.072169 * m_rgb_host[2];
    }

    Float mean() const override { return m_mean; }
    ScalarVector2f wavelength_range() const override { return m_range; }
    ScalarFloat max() const override {
        return is_spectral_v<Spectrum> ? m_mean * 4.f : dr::max(m_rgb_host); // only a bound is needed
    }

    std::string to_string() const override {
        return "FluoIlluminant[" + std::string(fluo::illuminant_to_string(*m_spectrum)) + "]";
    }

    MI_DECLARE_CLASS(FluoIlluminant)

private:
    static rust::Box<fluo::Illuminant> create(const Properties &props) {
        std::string name = fluo_detail::get_string(props, "illuminant", "");
        std::string file;
        if (props.has_property("filename"))
            file = mitsuba::file_resolver()->resolve(fs::path(fluo_detail::get_string(props, "filename", ""))).string();
        double scale = fluo_detail::get_float(Plugin, props, "scale", 1.0);
        bool normalize = props.get<bool>("normalize", true);
        return fluo_detail::rust_call(Plugin, [&] { return fluo::illuminant_new(name, file, scale, normalize); });
    }

    /// Zero everywhere (`scale` 0).
    static bool dark(const fluo::Illuminant &s) {
        rust::Vec<double> wavelengths, values;
        fluo::illuminant_nodes(s, wavelengths, values);
        return std::all_of(values.begin(), values.end(), [](double v) { return v == 0.0; });
    }

    /// The spectrum's nodes and values (from Rust, scale applied) as Mitsuba's own
    /// `regular` spectrum (a uniform grid, as the CIE tables) or `irregular` one: both
    /// interpolate linearly and are zero outside, as the Rust spectrum, so per-sample
    /// evaluation costs what a native spectrum costs (the values agree to float
    /// rounding; test_fluo_illuminant.py). nullptr if Mitsuba refuses the table (the
    /// constructor then raises an error).
    static ref<Texture> native_table(const fluo::Illuminant &s) {
        rust::Vec<double> wavelengths, values;
        fluo::illuminant_nodes(s, wavelengths, values);
        size_t n = wavelengths.size();
        if (n < 2 || values.size() != n)
            return nullptr;
        if (dark(s)) {
            // scale 0 (documented [0, inf)): a dark lamp, which Mitsuba's tables refuse
            // (nothing to sample): a uniform zero spectrum
            Properties p("uniform");
            p.set("value", 0.0);
            return PluginManager::instance()->create_object<Texture>(p);
        }
        auto join = [](const rust::Vec<double> &v) {
            std::ostringstream oss;
            oss.precision(9); // a float, exactly
            for (size_t i = 0; i < v.size(); ++i)
                oss << (i ? ", " : "") << (float) v[i];
            return oss.str();
        };
        double step = (wavelengths[n - 1] - wavelengths[0]) / (double) (n - 1);
        bool uniform = true;
        for (size_t i = 0; i < n; ++i)
            uniform &= std::abs(wavelengths[i] - (wavelengths[0] + step * (double) i)) <= 1e-6 * step;
        Properties p(uniform ? "regular" : "irregular");
        if (uniform) {
            p.set("wavelength_min", wavelengths[0]);
            p.set("wavelength_max", wavelengths[n - 1]);
        } else {
            p.set("wavelengths", join(wavelengths));
        }
        p.set("values", join(values));
        try {
            return PluginManager::instance()->create_object<Texture>(p);
        } catch (const std::exception &e) {
            if constexpr (dr::is_jit_v<Float>)
                Throw("%s: Mitsuba refused the spectrum's table, which this variant needs: %s", Plugin,
                      e.what());
            return nullptr;
        }
    }

    rust::Box<fluo::Illuminant> m_spectrum;
    ref<Texture> m_table; ///< spectral variants: the same spectrum as a native texture
    ScalarVector2f m_range;
    ScalarFloat m_mean;
    ScalarColor3f m_rgb_host; ///< linear sRGB (RGB variants), on the host
    Color3f m_rgb;
};

static const bool fluo_illuminant_registered =
    (fluo_detail::register_plugin<FluoIlluminant>("fluo_illuminant", ObjectType::Texture), true);

NAMESPACE_END(mitsuba)
