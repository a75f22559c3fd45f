// fluo_qd's parameters, substrate and dot index, parsed and sampled for Rust (fluo_qd.cpp,
// every variant).
#pragma once

#include <mitsuba/core/plugin.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/core/spectrum.h>
#include <mitsuba/render/interaction.h>
#include <mitsuba/render/ior.h>
#include <mitsuba/render/texture.h>

#include <algorithm>
#include <cmath>
#include <functional>
#include <initializer_list>
#include <sstream>
#include <string_view>
#include <string>
#include <utility>
#include <vector>

#include "fluo_common.h"
#include "fluo_bispectral.h"
#include "fluo_param_texture.h"

NAMESPACE_BEGIN(mitsuba)
NAMESPACE_BEGIN(fluo_detail)

/// A spectrum sampled for Rust: one value is a constant, several a table (nm, value).
struct QdSamples {
    std::vector<double> wavelengths, values;
    fluo::SampledSpectrum view() const {
        return { rust::Slice<const double>(wavelengths.data(), wavelengths.size()),
                 rust::Slice<const double>(values.data(), values.size()) };
    }
};

/// fluo_qd's substrate (a named conductor, eta/k, or a dielectric int_ior) and optional dot
/// index (qd_eta/qd_k), as Mitsuba textures of the variant, and their spectra for Rust.
template <typename Float, typename Spectrum> struct QdSetup {
    MI_IMPORT_TYPES(Texture)
    static constexpr const char *Plugin = "fluo_qd";
    /// Wavelengths standing for the RGB channels (dominant wavelengths of the sRGB primaries).
    static constexpr double RgbWavelengths[3] = { 611.0, 549.0, 464.0 };
    /// Step of the grid on which spectral substrate and dot indices are sampled for Rust, nm.
    static constexpr double SpectrumStepNm = 1.0;

    ref<Texture> eta, k, qd_eta, qd_k;
    std::string material; ///< named conductor substrate, or empty

    /// Read the numeric parameters (those `textured` names are skipped: the caller reads
    /// their textures), table_cos_nodes, distribution, the substrate and the dot index.
    void parse(const Properties &props, fluo::QdConfig &c, const std::function<bool(const char *)> &textured) {
        fluo::QdConstants &kc = c.constants;
        for (auto [name, field] : std::initializer_list<std::pair<const char *, double *>>{
                 { "radius", &c.radius }, { "width", &c.width }, { "quantum_yield", &c.quantum_yield },
                 { "density", &c.density }, { "ext_ior", &c.ext_ior }, { "lambda_min", &c.lambda_min },
                 { "lambda_max", &c.lambda_max }, { "alpha", &c.alpha }, { "table_step", &c.table_step },
                 { "gap_energy", &kc.gap_energy }, { "elementary_charge", &kc.elementary_charge },
                 { "planck", &kc.planck }, { "light_speed", &kc.light_speed }, { "boltzmann", &kc.boltzmann },
                 { "electron_mass", &kc.electron_mass }, { "hole_mass", &kc.hole_mass },
                 { "vacuum_permittivity", &kc.vacuum_permittivity },
                 { "relative_permittivity", &kc.relative_permittivity }, { "temperature", &kc.temperature } })
            if (!textured(name))
                *field = get_float<double>(Plugin, props, name, *field); // (constants span 1e-34..1e8)
        if (props.has_property("table_cos_nodes")) {
            int64_t rows = props.get<int64_t>("table_cos_nodes");
            if (rows < 2 || rows > 1025)
                Throw("%s: invalid parameter \"table_cos_nodes\" = %d: valid range is [2, 1025]", Plugin, rows);
            c.table_cos_nodes = (size_t) rows;
        }

        std::string distr = string::to_lower(std::string(props.get<std::string_view>("distribution", "beckmann")));
        c.ggx |= distr == "ggx";
        if (distr != "ggx" && distr != "beckmann")
            Throw("%s: invalid parameter \"distribution\" = \"%s\": valid values are \"beckmann\", \"ggx\"",
                  Plugin, distr);

        // Substrate: a named conductor, eta/k, or a dielectric int_ior (exactly one kind).
        bool has_material = props.has_property("material"),
             has_eta = props.has_property("eta") || props.has_property("k"), has_int = props.has_property("int_ior");
        if ((int) has_material + (int) has_eta + (int) has_int > 1)
            Throw("%s: specify one substrate: \"material\", \"eta\"/\"k\" or \"int_ior\"", Plugin);
        if (has_int) {
            double int_ior = lookup_ior(props, "int_ior", 1.5046f);
            if (!(int_ior > 0.0) || !std::isfinite(int_ior))
                Throw("%s: invalid parameter \"int_ior\" = %f: valid range is (0, inf)", Plugin, int_ior);
            eta = constant_texture(int_ior / c.ext_ior);
            k = constant_texture(0.0);
        } else if (has_material) {
            material = std::string(props.get<std::string_view>("material"));
            try {
                std::tie(eta, k) = conductor_textures(material);
            } catch (const std::exception &e) {
                Throw("%s: invalid parameter \"material\" = \"%s\": no conductor data for it (Mitsuba's "
                      "data/ior/%s.eta.spd and .k.spd; give \"eta\"/\"k\" spectra instead): %s",
                      Plugin, material, material, e.what());
            }
        } else {
            eta = props.get_unbounded_texture<Texture>("eta", 0.f);
            k = props.get_unbounded_texture<Texture>("k", 1.f);
        }
        if (props.has_property("qd_eta") != props.has_property("qd_k"))
            Throw("%s: specify both \"qd_eta\" and \"qd_k\" (the dot material's n and k) or neither", Plugin);
        if (props.has_property("qd_eta")) {
            qd_eta = props.get_unbounded_texture<Texture>("qd_eta");
            qd_k = props.get_unbounded_texture<Texture>("qd_k");
        }
    }

    bool uniform_substrate() const { return !eta->is_spatially_varying() && !k->is_spatially_varying(); }

    /// The spectra Rust builds a model from: the substrate's eta and k (sample_substrate)
    /// and the dot index (empty: built-in CdSe).
    void sample_all(const fluo::QdConfig &c, QdSamples &eta_s, QdSamples &k_s, QdSamples &qd_eta_s,
                    QdSamples &qd_k_s) const {
        sample_substrate(c, eta_s, k_s);
        if (qd_eta) {
            sample_texture(c, qd_eta.get(), qd_eta_s);
            sample_texture(c, qd_k.get(), qd_k_s);
        }
    }

    /// The substrate's spectral eta and k (each on its own grid, interpolated in Rust),
    /// for the coating's absorption tables: the eta/k textures in spectral variants; in
    /// RGB variants a named material's data files, else the piecewise-linear spectrum
    /// through the channel values at RgbWavelengths (what the per-channel elastic
    /// evaluation sees).
    void sample_substrate(const fluo::QdConfig &c, QdSamples &eta_s, QdSamples &k_s) const {
        if constexpr (!is_spectral_v<Spectrum>) {
            if (!material.empty()) {
                spectrum_from_file("data/ior/" + material + ".eta.spd", eta_s.wavelengths, eta_s.values);
                spectrum_from_file("data/ior/" + material + ".k.spd", k_s.wavelengths, k_s.values);
                return;
            }
            for (auto [tex, out] : { std::pair{ eta.get(), &eta_s }, std::pair{ k.get(), &k_s } }) {
                SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>();
                UnpolarizedSpectrum v = tex->eval(si, true);
                out->wavelengths = { RgbWavelengths[2], RgbWavelengths[1], RgbWavelengths[0] };
                out->values = { host_value(v[2]), host_value(v[1]), host_value(v[0]) };
            }
            return;
        }
        sample_texture(c, eta.get(), eta_s);
        sample_texture(c, k.get(), k_s);
    }

    /// Sample a texture at λ = lambda_min..lambda_max (spectral) or its channel mean (RGB).
    /// In the llvm/cuda variants the wavelengths are evaluated as one wide call.
    static void sample_texture(const fluo::QdConfig &c, const Texture *tex, QdSamples &out) {
        std::vector<double> &wavelengths = out.wavelengths, &values = out.values;
        wavelengths.clear();
        values.clear();
        if constexpr (is_spectral_v<Spectrum>) {
            size_t n = (size_t) std::ceil((c.lambda_max - c.lambda_min) / SpectrumStepNm) + 1;
            if (!(c.lambda_max > c.lambda_min) || n > 100000)
                n = 2; // invalid range: Rust rejects lambda_min/max with a proper message
            std::vector<float> lambda(n);
            for (size_t i = 0; i < n; ++i)
                lambda[i] = (float) std::min(c.lambda_min + (double) i * SpectrumStepNm,
                                             std::max(c.lambda_max, c.lambda_min + 1.0));
            std::vector<float> v = eval_at(tex, lambda);
            for (size_t i = 0; i < n; ++i) {
                double l = lambda[i];
                if (!wavelengths.empty() && !(l > wavelengths.back()))
                    continue;
                wavelengths.push_back(l);
                values.push_back(v[i]);
            }
            if (wavelengths.size() < 2) { // degenerate grid: a constant
                values.resize(1);
                wavelengths.resize(1);
            }
        } else {
            SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>();
            UnpolarizedSpectrum v = tex->eval(si, true);
            wavelengths.push_back(0.0);
            values.push_back(host_value(dr::mean(v)));
        }
    }

    /// A texture's values at the wavelengths `lambda` (spectral variants), four per
    /// interaction: one call per four wavelengths in scalar, one wide call in JIT variants.
    static std::vector<float> eval_at(const Texture *tex, const std::vector<float> &lambda) {
        constexpr size_t W = dr::size_v<Wavelength>;
        size_t n = lambda.size(), m = (n + W - 1) / W;
        std::vector<float> out(n);
        if constexpr (dr::is_jit_v<Float>) {
            SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>(m);
            for (size_t j = 0; j < W; ++j) {
                std::vector<float> w(m);
                for (size_t i = 0; i < m; ++i)
                    w[i] = lambda[std::min(i * W + j, n - 1)];
                si.wavelengths[j] = dr::load<Float>(w.data(), m);
            }
            UnpolarizedSpectrum v = tex->eval(si, true);
            dr::eval(v); // (one kernel for the four wavelengths)
            for (size_t j = 0; j < W; ++j) {
                std::vector<float> w = host_lanes(v[j], m); // (a uniform texture returns one value)
                for (size_t i = 0; i * W + j < n; ++i)
                    out[i * W + j] = w[i];
            }
        } else {
            for (size_t i = 0; i < n; i += W) {
                SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>();
                for (size_t j = 0; j < W; ++j)
                    si.wavelengths[j] = lambda[std::min(i + j, n - 1)];
                UnpolarizedSpectrum v = tex->eval(si, true);
                for (size_t j = 0; j < W && i + j < n; ++j)
                    out[i + j] = v[j];
            }
        }
        return out;
    }

    /// eta and k of a named conductor, taken from a native roughconductor built with the
    /// same `material` (so both read Mitsuba's data identically in every variant).
    static std::pair<ref<Texture>, ref<Texture>> conductor_textures(std::string_view name) {
        Properties p("roughconductor");
        p.set("material", std::string(name));
        ref<BSDF<Float, Spectrum>> rc = PluginManager::instance()->create_object<BSDF<Float, Spectrum>>(p);
        ref<Texture> eta, k;
        visit(rc.get(), [](std::string_view, void *, const std::type_info &) {}, [&](std::string_view key, Object *o) {
            if (key == "eta")
                eta = dynamic_cast<Texture *>(o);
            else if (key == "k")
                k = dynamic_cast<Texture *>(o);
            return false;
        });
        if (!eta || !k)
            Throw("%s: could not read the conductor data of material \"%s\"", Plugin, name);
        return { eta, k };
    }

    static ref<Texture> constant_texture(double value) {
        Properties p("uniform");
        p.set("value", value);
        return PluginManager::instance()->create_object<Texture>(p);
    }
};

/// fluo_qd's textured numeric parameters: `radius`, `density`, `quantum_yield` and `alpha`
/// each a float or a float texture; the textures' validated levels and the coating models
/// baked on them (fluo_qd.cpp's docs, "Textured parameters").
template <typename Float, typename Spectrum> struct QdTextures {
    MI_IMPORT_TYPES(Texture)
    enum Param { Radius, Density, Yield, Alpha, NParams };
    static constexpr const char *Names[NParams] = { "radius", "density", "quantum_yield", "alpha" };

    ref<Texture> tex[NParams]; ///< null: the float in the configuration
    bool given[NParams] = {};  ///< given as a texture (varying or not)
    std::vector<float> radii, densities, alphas; ///< the baked levels
    bool density_grid = false; ///< densities on a grid (more distinct values than its nodes)
    bool fluoresces = false;   ///< some texel has density > 0 and some Q > 0
    /// model (i, j, l) at index(i, j, l)
    std::vector<rust::Box<fluo::QdModel>> models;

    template <typename Config> static auto &field(Config &c, size_t i) { // (fluo::QdConfig, const or not)
        return i == Radius ? c.radius : i == Density ? c.density : i == Yield ? c.quantum_yield : c.alpha;
    }

    /// Read the four parameters' textures from props: a spatially varying one is kept, one
    /// that does not vary is read once into `c` (the uniform material's code path).
    void read(const Properties &props, fluo::QdConfig &c) {
        for (size_t i = 0; i < NParams; ++i) {
            const char *name = Names[i];
            if (!props.has_property(name) || props.type(name) != Properties::Type::Object)
                continue;
            ref<Texture> t = props.get_texture<Texture>(name);
            given[i] = true;
            if (t->is_spatially_varying())
                tex[i] = t;
            else
                field(c, i) = host_value(t->eval_1(dr::zeros<SurfaceInteraction3f>(), true));
            props.mark_queried(name);
        }
    }

    bool any() const { return tex[Radius] || tex[Density] || tex[Yield] || tex[Alpha]; }
    /// Whether parameter `name` was given as a texture (read by read(), not as a float).
    bool textured(const char *name) const {
        for (size_t i = 0; i < NParams; ++i)
            if (std::string_view(name) == Names[i] && given[i])
                return true;
        return false;
    }
    size_t index(size_t radius, size_t density, size_t alpha) const {
        return (radius * densities.size() + density) * alphas.size() + alpha;
    }

    /// Read and validate each texture's values (per texel for a bitmap, constituent values
    /// otherwise), then bake one model per (radius, density, alpha) level triple with Q = 1
    /// (the reradiation is linear in Q, which scales it per hit). Radii and alphas: the
    /// texture's own values. Densities: the texture's own values when at most
    /// TEXTURE_GRID_NODES, else that many nodes over their range. `c` takes the largest
    /// level of each (the base model). Nothing without textures.
    void bake(fluo::QdConfig &c, const QdSamples &eta, const QdSamples &k, const QdSamples &qd_eta,
              const QdSamples &qd_k) {
        constexpr const char *Plugin = "fluo_qd";
        if (!any()) {
            models.clear();
            return;
        }
        // Everything is built aside and kept only once it all succeeded: a rejected update
        // (an invalid texel, too many radii) leaves the previous models in place.
        std::vector<float> levels[NParams];
        bool grid = false;
        for (size_t i = 0; i < NParams; ++i) {
            if (!tex[i]) {
                levels[i] = { (float) field(c, i) };
                continue;
            }
            // radius and alpha bake their own models: their exact levels are needed; an
            // unreadable density or yield spans [0, its maximum] (a density grid)
            ParamLevels pl = param_levels(Plugin, Names[i], tex[i].get(), i == Radius || i == Alpha, true,
                                          [&](const std::vector<float> &v, size_t width) {
                                              rust_call(Plugin, [&] {
                                                  fluo::qd_check_values(Names[i],
                                                                        rust::Slice<const float>(v.data(), v.size()),
                                                                        width);
                                              });
                                          });
            levels[i] = std::move(pl.levels);
            if (i == Density && !pl.complete)
                grid = true;
        }
        for (Param i : { Radius, Alpha }) {
            size_t max = i == Radius ? fluo::qd_texture_max_radii() : fluo::qd_texture_max_alphas();
            if (levels[i].size() > max)
                Throw("%s: the \"%s\" texture holds %zu distinct values; at most %zu are supported (each %s bakes its "
                      "own coating %s: quantize the texture)", Plugin, Names[i], levels[i].size(), max,
                      i == Radius ? "radius" : "roughness", i == Radius ? "tables" : "models");
        }
        size_t nodes = fluo::qd_texture_grid_nodes();
        if (levels[Density].size() > nodes || grid) {
            float lo = levels[Density].front(), hi = levels[Density].back();
            levels[Density].clear();
            for (size_t j = 0; j < nodes; ++j)
                levels[Density].push_back(lo + (hi - lo) * (float) j / (float) (nodes - 1));
            levels[Density] = distinct_levels(levels[Density]);
            grid = true;
        }
        fluo::QdConfig b = c;
        b.quantum_yield = 1.0;
        std::vector<rust::Box<fluo::QdModel>> baked;
        for (float r : levels[Radius])
            for (float d : levels[Density])
                for (float a : levels[Alpha]) {
                    b.radius = r;
                    b.density = d;
                    b.alpha = a;
                    baked.push_back(
                        rust_call(Plugin, [&] { return fluo::qd_new(b, eta.view(), k.view(), qd_eta.view(), qd_k.view()); }));
                }
        models = std::move(baked);
        radii = levels[Radius];
        densities = levels[Density];
        alphas = levels[Alpha];
        density_grid = grid;
        fluoresces = levels[Yield].back() > 0.f && densities.back() > 0.f;
        for (size_t i = 0; i < NParams; ++i)
            field(c, i) = (double) levels[i].back();
    }

    std::string to_string() const {
        std::ostringstream oss;
        for (size_t i = 0; i < NParams; ++i)
            if (tex[i])
                oss << "  " << Names[i] << " = " << string::indent(tex[i]) << "," << std::endl;
        if (!models.empty())
            oss << "  baked models = " << models.size() << " (" << radii.size() << " radii x " << densities.size()
                << " densities" << (density_grid ? ", a grid" : "") << " x " << alphas.size() << " alphas),"
                << std::endl;
        return oss.str();
    }
};

NAMESPACE_END(fluo_detail)
NAMESPACE_END(mitsuba)
