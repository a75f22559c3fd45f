// fluo_jung's reflectance, `color` options (wide-gamut upsampling through a coefficient
// cube) and textured numeric parameters, parsed and checked at load (fluo_jung.cpp).
#pragma once

#include <mitsuba/core/fresolver.h>
#include <mitsuba/core/properties.h>

#include <optional>
#include <string>
#include <vector>

#include "fluo_common.h"
#include "fluo_param_texture.h"

NAMESPACE_BEGIN(mitsuba)
NAMESPACE_BEGIN(fluo_detail)

struct JungColorOptions {
    std::string space;     ///< color_space
    std::string cube_file; ///< resolved `cube`, or empty for the shipped cube
    std::string lookup;    ///< nearest | trilinear
    bool fluorescence = true;
    bool bilinear = false; ///< texel_interpolation = bilinear
    bool texture = false;  ///< `color` is a texture (else an <rgb> value)
};

/// Read fluo_jung's `color` options, refusing the parameters the cube sets and invalid
/// combinations with errors naming `plugin` and the parameter.
inline JungColorOptions jung_color_options(const char *plugin, const Properties &props) {
    for (const char *other :
         { "reflectance", "coefficients", "emission_peak", "stokes_shift", "concentration", "quantum_yield" })
        if (props.has_property(other))
            Throw("%s: \"color\" sets the reflectance and fluorescence through the cube; "
                  "do not also specify \"%s\"", plugin, other);
    JungColorOptions o;
    o.space = std::string(props.get<std::string_view>("color_space", "acescg"));
    o.cube_file = std::string(props.get<std::string_view>("cube", ""));
    if (!o.cube_file.empty())
        o.cube_file = mitsuba::file_resolver()->resolve(o.cube_file).string();
    o.lookup = std::string(props.get<std::string_view>("lookup", "nearest"));
    o.fluorescence = props.get<bool>("fluorescence", true);
    std::string interp(props.get<std::string_view>("texel_interpolation", "nearest"));
    if (interp != "nearest" && interp != "bilinear")
        Throw("%s: invalid parameter \"texel_interpolation\" = \"%s\": valid values are \"nearest\", "
              "\"bilinear\"", plugin, interp);
    o.bilinear = interp == "bilinear";
    o.texture = props.type("color") == Properties::Type::Object;
    if (!o.texture && props.type("color") != Properties::Type::Color)
        Throw("%s: \"color\" must be an <rgb> value or a bitmap texture", plugin);
    if (o.bilinear && !o.texture)
        Throw("%s: \"texel_interpolation\" applies to a \"color\" texture, not to a constant colour", plugin);
    return o;
}

/// fluo_jung's elastic reflectance when no `color` is given: sigmoid `coefficients` (set in
/// `config`; returns null) or a `reflectance` texture (default 0.5), checked to lie in [0, 1].
template <typename Texture>
ref<Texture> jung_reflectance(const char *plugin, const Properties &props, fluo::JungConfig &config) {
    config.has_coefficients = props.has_property("coefficients");
    if (!config.has_coefficients) {
        ref<Texture> r = props.get_texture<Texture>("reflectance", .5f);
        check_texture_range(plugin, "reflectance", r.get(), 0.0, 1.0);
        return r;
    }
    if (props.has_property("reflectance"))
        Throw("%s: specify either \"reflectance\" or \"coefficients\", not both", plugin);
    auto c = parse_list<3>(plugin, "coefficients", std::string(props.get<std::string_view>("coefficients")));
    std::tie(config.c0, config.c1, config.c2) = std::make_tuple(c[0], c[1], c[2]);
    return nullptr;
}

/// fluo_jung's numeric parameters that take a float texture, in this order.
enum JungParam { JungPeak, JungShift, JungConc, JungYield, JungParams };
inline constexpr const char *JungParamNames[JungParams] = { "emission_peak", "stokes_shift", "concentration",
                                                            "quantum_yield" };

/// Read fluo_jung's numeric parameters (unless `color` sets them): a float into `config`,
/// a spatially varying float texture into `tex` (a texture that does not vary is read
/// once as its float).
template <typename Float, typename Spectrum>
void jung_param_textures(const char *plugin, const Properties &props, fluo::JungConfig &config,
                         ref<Texture<Float, Spectrum>> (&tex)[JungParams]) {
    using SurfaceInteraction3f = SurfaceInteraction<Float, Spectrum>;
    double *fields[JungParams] = { &config.emission_peak, &config.stokes_shift, &config.concentration,
                                   &config.quantum_yield };
    for (size_t i = 0; i < JungParams && !props.has_property("color"); ++i) {
        const char *name = JungParamNames[i];
        if (props.has_property(name) && props.type(name) == Properties::Type::Object) {
            ref<Texture<Float, Spectrum>> t = props.get_texture<Texture<Float, Spectrum>>(name);
            if (t->is_spatially_varying())
                tex[i] = t;
            else
                *fields[i] = (double) dr::slice(t->eval_1(dr::zeros<SurfaceInteraction3f>(), true), 0);
        } else {
            *fields[i] = get_float(plugin, props, name, *fields[i]);
        }
    }
}

/// Textured parameters' values, read and validated at load: the levels of λe and s (each
/// (λe, s) pair is a dye shape), whether any texel has c > 0 and any Q > 0, and the shapes.
struct JungShapeSet {
    std::vector<float> peaks, shifts; ///< sorted distinct validated values
    bool fluoresce = false;
    std::optional<rust::Box<fluo::JungShapes>> shapes; ///< one per (λe, s), peak-major
};

/// Read and validate every textured parameter's values (per texel for a bitmap, the
/// constituent values otherwise; Rust names a bad texel) and build one dye shape per
/// (λe, s) pair the textures can combine. `config` takes a representative value of each
/// textured parameter, so that the base model (the sigmoid reflectance) stays valid.
/// Without textures: nullopt.
template <typename Float, typename Spectrum>
std::optional<JungShapeSet> jung_shape_set(const char *plugin, const ref<Texture<Float, Spectrum>> (&tex)[JungParams],
                                           fluo::JungConfig &config) {
    bool any = false;
    for (auto &t : tex)
        any |= (bool) t;
    if (!any)
        return std::nullopt;
    std::vector<float> levels[JungParams];
    bool fluoresces[2] = { config.concentration > 0.0, config.quantum_yield > 0.0 };
    double *fields[JungParams] = { &config.emission_peak, &config.stokes_shift, &config.concentration,
                                   &config.quantum_yield };
    for (size_t i = 0; i < JungParams; ++i) {
        if (!tex[i]) {
            levels[i] = { (float) *fields[i] };
            continue;
        }
        // λe and s select dye shapes: their exact levels are needed
        levels[i] = param_levels(plugin, JungParamNames[i], tex[i].get(), i == JungPeak || i == JungShift, false,
                                 [&](const std::vector<float> &v, size_t width) {
                                     rust_call(plugin, [&] {
                                         fluo::jung_check_values(JungParamNames[i],
                                                                 rust::Slice<const float>(v.data(), v.size()), width);
                                     });
                                 }).levels;
        *fields[i] = (double) levels[i].back();
        if (i == JungConc || i == JungYield)
            fluoresces[i - JungConc] = levels[i].back() > 0.f;
    }
    JungShapeSet out;
    out.fluoresce = fluoresces[0] && fluoresces[1];
    out.peaks = levels[JungPeak];
    out.shifts = levels[JungShift];
    std::vector<double> peaks(out.peaks.begin(), out.peaks.end()), shifts(out.shifts.begin(), out.shifts.end());
    out.shapes = rust_call(plugin, [&] {
        return fluo::jung_shapes_new(rust::Slice<const double>(peaks.data(), peaks.size()),
                                     rust::Slice<const double>(shifts.data(), shifts.size()));
    });
    config.emission_peak = peaks[0];
    config.stokes_shift = shifts[0];
    return out;
}

NAMESPACE_END(fluo_detail)
NAMESPACE_END(mitsuba)
