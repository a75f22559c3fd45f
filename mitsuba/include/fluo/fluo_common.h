// Shared helpers for the fluo Mitsuba plugins.
//
// The plugins parse Mitsuba Properties and hand the numbers to the Rust core through the
// cxx bridge (fluo-mitsuba/src/bridge.rs.h) at load and on parameter updates; Rust
// validates them and bakes what the plugins evaluate per lane at render time (Dr.Jit
// cannot trace calls into Rust, and no variant calls Rust per vertex).
#pragma once

#include <mitsuba/core/logger.h>
#include <mitsuba/core/plugin.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/core/spectrum.h>

#include <array>
#include <atomic>
#include <deque>
#include <string>
#include <string_view>

#include "fluo-mitsuba/src/bridge.rs.h"
#include "rust/cxx.h"

NAMESPACE_BEGIN(mitsuba)
NAMESPACE_BEGIN(fluo_detail)

/// Call into Rust; a Rust error (cxx's rust::Error) becomes a Mitsuba exception
/// that names the plugin and carries the Rust message.
template <typename F> auto rust_call(const char *plugin, F &&f) -> decltype(f()) {
    try {
        return f();
    } catch (const rust::Error &e) {
        Throw("%s: %s", plugin, e.what());
    }
}

/// Read a scalar float property with a default, rejecting non-numeric input with a
/// message that names the parameter.
inline double get_float(const char *plugin, const Properties &props, const char *name, double def) {
    if (!props.has_property(name))
        return def;
    try {
        return (double) props.get<float>(name);
    } catch (const std::exception &e) {
        Throw("%s: parameter \"%s\" must be a number (%s)", plugin, name, e.what());
    }
}

/// A string parameter, `def` when absent.
inline std::string get_string(const Properties &props, const char *name, const char *def) {
    return props.has_property(name) ? std::string(props.get<std::string_view>(name)) : def;
}

/// A parameter update as a transaction: `apply()` copies the traversed values into
/// `config` and `rebuild()` validates it in Rust and re-derives everything from it. If
/// either throws, `config` is restored and rebuilt (which also resets the traversed
/// values, so `mi.traverse` shows the old state) and the error propagates: a rejected
/// update leaves the object exactly as it was, and later valid updates work.
template <typename Config, typename Apply, typename Rebuild>
void transactional_update(Config &config, Apply &&apply, Rebuild &&rebuild) {
    const Config previous = config;
    try {
        apply();
        rebuild();
    } catch (...) {
        config = previous;
        rebuild();
        throw;
    }
}

/// Check that a reflectance-like texture stays within [lo, hi]: its mean and, where the
/// texture reports one, its maximum (a constant, an <rgb>, a bitmap's largest texel).
/// NaN, ±inf and out-of-range values are rejected naming the parameter, since Mitsuba
/// itself accepts any float and a NaN reflectance renders an all-NaN image.
template <typename Texture>
void check_texture_range(const char *plugin, const char *name, const Texture *tex, double lo, double hi) {
    if (!tex)
        return;
    auto check = [&](double v, const char *what) {
        if (!(v >= lo && v <= hi))
            Throw("%s: invalid parameter \"%s\" = %g (%s): valid range is [%g, %g]", plugin, name, v, what,
                  lo, hi);
    };
    double mean = 0.0, max = 0.0;
    bool has_mean = true, has_max = true;
    try { mean = (double) dr::slice(tex->mean()); } catch (const std::exception &) { has_mean = false; }
    try { max = (double) tex->max(); } catch (const std::exception &) { has_max = false; }
    if (has_mean)
        check(mean, "its mean");
    if (has_max)
        check(max, "its maximum");
}

/// Allowed range of the integrators' `lambda_min`, nm.
constexpr double LambdaMinLo = 200.0, LambdaMinHi = 360.0;

/// The integrators' `lambda_min` (nm): where spectrally defined emitters reach below the
/// camera's 360 nm, validated against [LambdaMinLo, LambdaMinHi].
inline double lambda_min_of(const char *plugin, const Properties &props) {
    double lambda_min = get_float(plugin, props, "lambda_min", 300.0);
    if (!(lambda_min >= LambdaMinLo && lambda_min <= LambdaMinHi))
        Throw("%s: invalid parameter \"lambda_min\" = %f: valid range is [%.0f, %.0f] nm", plugin, lambda_min,
              LambdaMinLo, LambdaMinHi);
    return lambda_min;
}

/// Reduced RGB transport's warning for an emitter whose radiance is mostly ultraviolet.
inline void warn_uv_emitter(const char *plugin, const char *variant, const Object *emitter) {
    std::string name = emitter->id().empty() ? std::string(emitter->class_name()) : std::string(emitter->id());
    Log(Warn, "%s (%s): emitter %s is mostly ultraviolet; reduced transport carries it in one UV band, which "
              "can misstate UV-excited fluorescence several times over (a narrow 365 nm lamp: ~5x too dark, see "
              "`fluo-rs saturated-report`). Render UV-lit scenes in a spectral variant where that matters.",
        plugin, variant, name);
}

/// Parse "a, b, c" (commas and/or spaces) into exactly N doubles.
template <size_t N>
std::array<double, N> parse_list(const char *plugin, const char *name, const std::string &text) {
    std::array<double, N> out{};
    std::string s = text;
    for (char &c : s)
        if (c == ',')
            c = ' ';
    const char *p = s.c_str();
    size_t n = 0;
    while (true) {
        while (*p == ' ' || *p == '\t' || *p == '\n')
            ++p;
        if (*p == '\0')
            break;
        char *end = nullptr;
        double v = std::strtod(p, &end);
        if (end == p || n == N)
            Throw("%s: parameter \"%s\" = \"%s\" must be a list of %zu numbers", plugin, name,
                  text, N);
        out[n++] = v;
        p = end;
    }
    if (n != N)
        Throw("%s: parameter \"%s\" = \"%s\" must be a list of %zu numbers (got %zu)", plugin, name,
              text, N, n);
    return out;
}

/// The variants every plugin serves (register_plugin in fluo_bispectral.h registers each class
/// template for all of them); every other variant of the wheel gets a stub.
inline bool served_variant(std::string_view variant) {
    return variant == "scalar_rgb" || variant == "scalar_spectral" || variant == "llvm_ad_rgb" ||
           variant == "llvm_ad_spectral" || variant == "cuda_ad_rgb" || variant == "cuda_ad_spectral" ||
           variant == "scalar_spectral_polarized" || variant == "llvm_ad_spectral_polarized" ||
           variant == "cuda_ad_spectral_polarized";
}

/// Register, for every variant of the wheel (MI_VARIANTS) that the plugins do not
/// serve, a factory that raises a clear error naming the plugin and the variant:
/// without it Mitsuba reports a plugin "not found", as if fluo were not loaded.
inline void register_unavailable(const char *name, ObjectType type) {
    struct Unavailable {
        std::string name, variant;
    };
    static std::deque<Unavailable> entries; // stable addresses: the factories' payloads
    std::string_view all = MI_VARIANTS;
    while (!all.empty()) {
        size_t end = all.find('\n');
        std::string_view variant = all.substr(0, end);
        all = end == std::string_view::npos ? std::string_view() : all.substr(end + 1);
        if (variant.empty() || served_variant(variant))
            continue;
        entries.push_back({ name, std::string(variant) });
        PluginManager::instance()->register_plugin(
            name, variant, type,
            [](void *payload, const Properties &) -> ref<Object> {
                auto *u = static_cast<const Unavailable *>(payload);
                Throw("%s: not available in variant \"%s\"; fluo's plugins run in scalar_rgb, "
                      "scalar_spectral, scalar_spectral_polarized, llvm_ad_rgb, llvm_ad_spectral, "
                      "llvm_ad_spectral_polarized and the cuda_ad ones of those (e.g. "
                      "mi.set_variant(\"scalar_spectral\"))",
                      u->name, u->variant);
            },
            nullptr, &entries.back());
    }
}

NAMESPACE_END(fluo_detail)

/// A texture that knows its emission spectrum (fluo_illuminant), so that reduced
/// transport can use the spectrum's own basis coefficients, including the UV band.
class SpectralSource {
public:
    virtual ~SpectralSource() = default;
    virtual const fluo::Illuminant &illuminant() const = 0;
    /// Luminance of the RGB value the texture evaluates to in the RGB variants (never 0).
    virtual double rgb_luminance() const = 0;
};

NAMESPACE_END(mitsuba)
