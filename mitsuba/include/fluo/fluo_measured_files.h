// The files of the measured-material plugins fluo_matrix and fluo_gmm: one "filename", or
// several ("filename0", "filename1", ...) selected per hit by a material-index texture
// "index": read, resolved and validated once at load (fluo_measured.cpp).
#pragma once

#include <mitsuba/core/fresolver.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/render/texture.h>

#include <string>
#include <vector>

#include "fluo_common.h"
#include "fluo_param_texture.h"

NAMESPACE_BEGIN(mitsuba)
NAMESPACE_BEGIN(fluo_detail)

template <typename Float, typename Spectrum> struct MeasuredFiles {
    MI_IMPORT_TYPES(Texture)
    using Factory = rust::Box<fluo::MeasuredModel> (*)(rust::Str);

    std::vector<std::string> keys;  ///< "filename", or "filename0", "filename1", ...
    std::vector<std::string> paths; ///< the resolved files
    std::vector<rust::Box<fluo::MeasuredModel>> models;
    ref<Texture> index; ///< the material-index texture (null: one file)

    /// Read the files named in `props` with `factory` (Rust validates each); errors name
    /// `plugin`, the parameter and the file.
    MeasuredFiles(const Properties &props, const char *plugin, Factory factory) {
        std::vector<std::string> names;
        if (props.has_property("filename"))
            names.emplace_back(props.get<std::string_view>("filename"));
        for (size_t i = 0;; ++i) {
            std::string key = "filename" + std::to_string(i);
            if (!props.has_property(key))
                break;
            names.emplace_back(props.get<std::string_view>(key));
            keys.push_back(key);
        }
        if (names.empty())
            Throw("%s: parameter \"filename\" is required (or \"filename0\", \"filename1\", ... with "
                  "a material-index texture \"index\")", plugin);
        if (props.has_property("filename") && !keys.empty())
            Throw("%s: specify either \"filename\" or \"filename0\", \"filename1\", ..., not both", plugin);
        if (keys.empty())
            keys.push_back("filename");
        if (keys.size() > 1 || props.has_property("index")) {
            if (!props.has_property("index"))
                Throw("%s: several files (\"filename0\" ...) need a material-index texture \"index\"", plugin);
            index = props.get_texture<Texture>("index");
        }
        for (size_t i = 0; i < names.size(); ++i) {
            fs::path path = file_resolver()->resolve(names[i]);
            if (!fs::exists(path))
                Throw("%s: invalid parameter \"%s\" = \"%s\": file not found", plugin, keys[i], names[i]);
            paths.push_back(path.string());
            models.push_back(rust_call(plugin, [&] { return factory(rust::Str(paths.back())); }));
        }
        if (index)
            check_index(plugin, index.get(), models.size());
    }

    /// Every texel (or constituent value) of the index texture is a whole number in
    /// [0, count − 1].
    static void check_index(const char *plugin, const Texture *tex, size_t count) {
        TextureValues<Float, Spectrum> tv(plugin, "index", tex);
        if (!tv.complete)
            Throw("%s: the material-index texture's values cannot be read at load (%s): use a bitmap, a "
                  "constant or a texture of those (checkerboard)", plugin, tex->class_name());
        rust_call(plugin, [&] {
            fluo::measured_check_index(rust::Slice<const float>(tv.values.data(), tv.values.size()), tv.width,
                                       count);
        });
    }
};

NAMESPACE_END(fluo_detail)
NAMESPACE_END(mitsuba)
