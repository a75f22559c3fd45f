// Numeric plugin parameters given as float textures (fluo_jung's emission_peak,
// stokes_shift, concentration, quantum_yield): what load-time validation can read of a
// texture, and the per-hit lookup of a parameter whose values select among models built
// at load.
#pragma once

#include <drjit/tensor.h>
#include <mitsuba/core/object.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/render/interaction.h>
#include <mitsuba/render/texture.h>

#include <algorithm>
#include <cmath>
#include <string>
#include <string_view>
#include <typeinfo>
#include <unordered_set>
#include <vector>

#include "fluo_common.h"

NAMESPACE_BEGIN(mitsuba)
NAMESPACE_BEGIN(fluo_detail)

/// The values a float texture can take, as far as they can be read at load:
/// - a bitmap: every texel (`width` > 0, row-major from the top row; one channel only,
///   as a grayscale image or single-channel EXR is loaded);
/// - a constant texture: its value;
/// - any other texture (a checkerboard, ...): the union of the values of the textures it
///   holds (a checkerboard's color0 and color1), read recursively.
/// `complete` is false when some texture below has values that cannot be read (a
/// procedural texture with no texture children, say): then only its mean and maximum
/// are known.
template <typename Float, typename Spectrum> struct TextureValues {
    MI_IMPORT_TYPES(Texture)

    std::vector<float> values;
    size_t width = 0;   ///< > 0: `values` are the texels of one bitmap of this width
    bool complete = true;

    /// Read `tex`; errors name `plugin` and `name`.
    TextureValues(const char *plugin, const char *name, const Texture *tex) {
        std::unordered_set<const Object *> seen;
        read(plugin, name, tex, seen, true);
    }

private:
    void read(const char *plugin, const char *name, const Texture *tex, std::unordered_set<const Object *> &seen,
              bool top) {
        if (!tex || !seen.insert(tex).second)
            return;
        if (!tex->is_spatially_varying()) {
            SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>();
            values.push_back((float) dr::slice(tex->eval_1(si, true), 0));
            return;
        }
        // the bitmap data (stored in single, half or double precision: an 8-bit image is kept
        // in half precision in RGB variants) and child textures the texture's traverse() reports
        const TensorXf *data = nullptr;
        const TensorXf16 *data16 = nullptr;
        const TensorXf64 *data64 = nullptr;
        std::vector<const Texture *> children;
        auto value = [&](std::string_view key, void *ptr, const std::type_info &type) {
            if (key != "data")
                return;
            if (type == typeid(TensorXf))
                data = static_cast<const TensorXf *>(ptr);
            else if (type == typeid(TensorXf16))
                data16 = static_cast<const TensorXf16 *>(ptr);
            else if (type == typeid(TensorXf64))
                data64 = static_cast<const TensorXf64 *>(ptr);
        };
        visit(const_cast<Texture *>(tex), value, [&](std::string_view, Object *o) {
            if (auto *t = dynamic_cast<const Texture *>(o))
                children.push_back(t);
            return false;
        });
        auto texels = [&](const auto &t) {
            if (t.ndim() != 3 || t.shape(2) != 1)
                Throw("%s: parameter \"%s\" is a texture with %zu channels; a textured numeric parameter "
                      "needs one channel (a grayscale image, or a single-channel EXR)",
                      plugin, name, t.ndim() == 3 ? t.shape(2) : (size_t) 0);
            if (top)
                width = t.shape(1);
            std::vector<float> host = host_floats(t); // (one read-back, not one per texel)
            values.insert(values.end(), host.begin(), host.end());
        };
        if (data || data16 || data64) {
            if (data)
                texels(*data);
            else if (data16)
                texels(*data16);
            else
                texels(*data64);
            return;
        }
        if (children.empty()) {
            complete = false;
            return;
        }
        for (const Texture *c : children)
            read(plugin, name, c, seen, false);
    }
};

/// The sorted distinct values of `v`.
inline std::vector<float> distinct_levels(std::vector<float> v) {
    std::sort(v.begin(), v.end());
    v.erase(std::unique(v.begin(), v.end()), v.end());
    return v;
}

/// The values of a textured numeric parameter, read and checked at load: every texel
/// or constituent value goes through `check(values, width)` (the plugin's Rust check,
/// which names the texel). A texture whose values cannot be read is refused when the
/// plugin needs its exact levels (`exact`); otherwise it is range-checked in [0, 1]
/// through its mean and maximum and stands for {0 (if `from_zero`), its maximum}, and
/// `complete` says so. `levels` are sorted and distinct, never empty.
struct ParamLevels {
    std::vector<float> levels;
    bool complete = true;
};

template <typename Float, typename Spectrum, typename Check>
ParamLevels param_levels(const char *plugin, const char *name, const Texture<Float, Spectrum> *tex, bool exact,
                         bool from_zero, Check &&check) {
    TextureValues<Float, Spectrum> tv(plugin, name, tex);
    check(tv.values, tv.width);
    ParamLevels out;
    out.complete = tv.complete;
    if (!tv.complete) {
        if (exact)
            Throw("%s: parameter \"%s\" is a texture whose values cannot be read at load (%s); a textured "
                  "%s must be a bitmap, a constant or a texture of those (checkerboard)",
                  plugin, name, tex->class_name(), name);
        check_texture_range(plugin, name, tex, 0.0, 1.0);
        if (from_zero)
            tv.values.push_back(0.f); // its minimum is not known
        tv.values.push_back((float) tex->max());
    }
    out.levels = distinct_levels(std::move(tv.values));
    if (out.levels.empty())
        Throw("%s: parameter \"%s\" is a texture without values", plugin, name);
    return out;
}

NAMESPACE_END(fluo_detail)
NAMESPACE_END(mitsuba)
