// fluo_jung's reflectance and `color` options (wide-gamut upsampling through a coefficient
// cube), parsed and checked once for the scalar shim (fluo_jung.cpp) and the vectorised
// one (fluo_jung_jit.cpp).
#pragma once

#include <mitsuba/core/fresolver.h>
#include <mitsuba/core/properties.h>

#include <string>

#include "fluo_common.h"

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
    config.c0 = c[0];
    config.c1 = c[1];
    config.c2 = c[2];
    return nullptr;
}

NAMESPACE_END(fluo_detail)
NAMESPACE_END(mitsuba)
