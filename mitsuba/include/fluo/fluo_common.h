// Shared helpers for the fluo Mitsuba plugin shims.
//
// The shims are thin: they parse Mitsuba Properties, hand the numbers to the Rust
// core through the cxx bridge (fluo-mitsuba/src/bridge.rs.h), and evaluate Mitsuba textures.
// They serve the scalar variants only (Dr.Jit cannot trace calls into Rust).
#pragma once

#include <mitsuba/core/logger.h>
#include <mitsuba/core/plugin.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/core/spectrum.h>

#include <array>
#include <atomic>
#include <cstring>
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

/// Wavelengths of a spectral-variant interaction as a float array.
template <typename Wavelength> std::array<float, 4> wavelengths_of(const Wavelength &w) {
    std::array<float, 4> out{};
    for (size_t i = 0; i < 4; ++i)
        out[i] = w[i];
    return out;
}

/// A per-thread memo of a pure function of four wavelengths, for a BSDF asked the same
/// value several times at a vertex. One entry per thread and call site (each `compute`
/// lambda has its own type, hence its own entry), keyed by a model build number
/// (next_build(), never reused: a rebuilt or reallocated model cannot hit a stale
/// entry) and the wavelengths, bitwise; a miss calls `compute(values)`.
class WavelengthMemo {
public:
    static uint64_t next_build() {
        static std::atomic<uint64_t> counter{ 0 };
        return ++counter;
    }
    template <typename F>
    static const std::array<float, 4> &get(uint64_t build, const std::array<float, 4> &lambda, F &&compute) {
        thread_local Entry entry;
        if (entry.build != build || std::memcmp(entry.lambda.data(), lambda.data(), sizeof(lambda)) != 0) {
            entry.build = 0; // invalid until computed (compute may throw)
            compute(entry.values);
            entry.lambda = lambda;
            entry.build = build;
        }
        return entry.values;
    }

private:
    struct Entry {
        uint64_t build = 0;
        std::array<float, 4> lambda{}, values{};
    };
};

inline rust::Slice<const float> slice(const std::array<float, 4> &a) {
    return rust::Slice<const float>(a.data(), a.size());
}
inline rust::Slice<float> slice_mut(std::array<float, 4> &a) {
    return rust::Slice<float>(a.data(), a.size());
}

/// The plugins that also run in the vectorised variants (fluo_jit.h registers them).
inline bool jit_plugin(std::string_view name) {
    return name == "fluo_illuminant" || name == "fluo_jung" || name == "fluo_path" || name == "fluo_matrix" ||
           name == "fluo_gmm" || name == "fluo_qd" || name == "fluo_qd_medium" || name == "fluo_dye_medium" ||
           name == "fluo_volpath";
}

/// Whether plugin `name` serves `variant`; every other variant of the wheel gets a stub.
inline bool served_variant(std::string_view name, std::string_view variant) {
    if (variant == "scalar_rgb" || variant == "scalar_spectral")
        return true;
    return jit_plugin(name) && (variant == "llvm_ad_rgb" || variant == "llvm_ad_spectral" ||
                                variant == "cuda_ad_rgb" || variant == "cuda_ad_spectral");
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
        if (variant.empty() || served_variant(name, variant))
            continue;
        entries.push_back({ name, std::string(variant) });
        PluginManager::instance()->register_plugin(
            name, variant, type,
            [](void *payload, const Properties &) -> ref<Object> {
                auto *u = static_cast<const Unavailable *>(payload);
                Throw("%s: not available in variant \"%s\" yet; fluo's plugins run in scalar_rgb and "
                      "scalar_spectral (mi.set_variant(\"scalar_spectral\") or \"scalar_rgb\"), and "
                      "fluo_illuminant, fluo_jung, fluo_matrix, fluo_gmm, fluo_qd, fluo_qd_medium, fluo_dye_medium, fluo_volpath and "
                      "fluo_path also in llvm_ad_rgb, "
                      "llvm_ad_spectral, cuda_ad_rgb and "
                      "cuda_ad_spectral",
                      u->name, u->variant);
            },
            nullptr, &entries.back());
    }
}

/// Register plugin class template T for the two scalar variants.
template <template <typename, typename> class T>
void register_scalar_plugin(const char *name, ObjectType type) {
    fluo::note_plugin(name, type == ObjectType::BSDF ? "bsdf"
                            : type == ObjectType::Integrator ? "integrator"
                            : type == ObjectType::Medium     ? "medium"
                                                             : "texture",
                      jit_plugin(name));
    PluginManager *pm = PluginManager::instance();
    register_unavailable(name, type);
    pm->register_plugin(
        name, "scalar_rgb", type,
        [](void *, const Properties &p) -> ref<Object> { return new T<float, Color<float, 3>>(p); },
        nullptr, nullptr);
    pm->register_plugin(
        name, "scalar_spectral", type,
        [](void *, const Properties &p) -> ref<Object> { return new T<float, Spectrum<float, 4>>(p); },
        nullptr, nullptr);
}

NAMESPACE_END(fluo_detail)
NAMESPACE_END(mitsuba)
