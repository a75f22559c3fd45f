// Scene scanning for fluo_path and fluo_volpath (every variant): walking the scene graph,
// the fluorescent BSDFs and media they transport, and the BSDF wrappers (twosided,
// blendbsdf, mask, normalmap, bumpmap; nested too) that they see through, per lane, to the
// fluorescent material acting at a vertex.
#pragma once

#include <mitsuba/core/plugin.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/film.h>
#include <mitsuba/render/interaction.h>
#include <mitsuba/render/sampler.h>
#include <mitsuba/render/sensor.h>
#include <mitsuba/render/texture.h>

#include <algorithm>
#include <optional>
#include <string>
#include <string_view>
#include <unordered_map>
#include <unordered_set>
#include <tuple>
#include <utility>
#include <atomic>
#include <mutex>
#include <vector>

#include "fluo_bispectral.h"

NAMESPACE_BEGIN(mitsuba)
NAMESPACE_BEGIN(fluo_detail)

/// Power heuristic, as in path.cpp (non-finite weights become 0), without gradients (as
/// Mitsuba's integrators: MIS weights are not differentiated).
template <typename Float> Float mis_weight(const Float &pdf_a, const Float &pdf_b) {
    Float a = dr::detach<true>(pdf_a), b = dr::detach<true>(pdf_b);
    a *= a;
    b *= b;
    Float w = a / (a + b);
    return dr::select(dr::isfinite(w), w, 0.f);
}

/// Collects every object reachable from a root (each once).
struct Collector : TraversalCallback {
    std::vector<Object *> objects;
    std::unordered_set<Object *> seen;
    void visit(Object *o) {
        if (!o || !seen.insert(o).second)
            return;
        objects.push_back(o);
        o->traverse(this);
    }
    void put_value(std::string_view, void *, uint32_t, const std::type_info &) override {}
    void put_object(std::string_view, Object *o, uint32_t) override { visit(o); }
};

/// The scene's media implementing interface M (shapes' interiors and exteriors, sensors'),
/// each once, marked as managed by the integrator asking (fluo_volpath in every variant).
template <typename M, typename Scene> std::vector<const M *> managed_media(const Scene *scene) {
    std::vector<const M *> media;
    auto add = [&](const auto *m) {
        if (auto *b = dynamic_cast<const M *>(m)) {
            b->set_managed(true);
            if (std::find(media.begin(), media.end(), b) == media.end())
                media.push_back(b);
        }
    };
    for (const auto &shape : scene->shapes()) {
        add(shape->interior_medium());
        add(shape->exterior_medium());
    }
    for (const auto &sensor : scene->sensors())
        add(sensor->medium());
    return media;
}

/// Every object reachable from the scene's shapes (their BSDFs, wrapped ones, textures).
template <typename Scene> Collector shape_objects(const Scene *scene) {
    Collector c;
    for (const auto &shape : scene->shapes())
        c.visit(const_cast<Object *>(static_cast<const Object *>(shape.get())));
    return c;
}

/// Sets a flag for its lifetime (an integrator's derivative pass: render_forward/backward).
struct Raised {
    bool &flag;
    explicit Raised(bool &f) : flag(f) { flag = true; }
    ~Raised() { flag = false; }
};

/// fluo_path and fluo_volpath prepare a render in render(); nested in another integrator
/// whose render() calls only their sample() (`stokes`, `moment`; `aov` calls render()) the
/// first sample of a scene prepares it instead, under a lock (the scalar variants sample
/// from many threads), and again after any update of one of fluo's plugins
/// (update_generation), so that the joined tables, ranges and reduced operators follow it.
/// Mitsuba's own plugins are read live, except an emitter's spectral range: after updating
/// that, render with fluo_path itself.
class PreparedScene {
public:
    template <typename Prepare> void ensure(const void *scene, Prepare &&prepare) {
        uint64_t generation = update_generation().load(std::memory_order_acquire);
        if (m_scene.load(std::memory_order_acquire) == scene &&
            m_generation.load(std::memory_order_acquire) == generation)
            return;
        std::lock_guard<std::mutex> guard(m_mutex);
        if (m_scene.load(std::memory_order_relaxed) != scene ||
            m_generation.load(std::memory_order_relaxed) != generation) {
            prepare();
            m_generation.store(generation, std::memory_order_release);
            m_scene.store(scene, std::memory_order_release);
        }
    }
    /// A render prepared `scene` itself (render()), as of the updates so far.
    void mark(const void *scene) {
        m_generation.store(update_generation().load(std::memory_order_acquire), std::memory_order_release);
        m_scene.store(scene, std::memory_order_release);
    }

private:
    std::atomic<const void *> m_scene{ nullptr };
    std::atomic<uint64_t> m_generation{ 0 };
    std::mutex m_mutex;
};

/// The fluorescent BSDFs among `c`'s objects (interface B, whose jit_fluorescent() holds),
/// wrapped ones included (FluoWrappers::scan refuses the wrappers it cannot see through);
/// every bispectral one is marked as transported this render.
template <typename B> std::vector<B *> fluorescent_bsdfs(const Collector &c) {
    std::vector<B *> out;
    for (Object *o : c.objects) {
        auto *b = dynamic_cast<B *>(o);
        if (!b)
            continue;
        b->set_managed(true);
        if (b->jit_fluorescent())
            out.push_back(b);
    }
    return out;
}

/// Spectral variants: drop from `bsdfs` the materials whose excitation band misses the
/// render's range [lo, hi] (the scene's light never reaches it: a plain BSDF there).
/// Returns whether a remaining one has a direction-dependent reradiation lobe.
template <typename Spectrum, typename B> bool keep_excited(std::vector<B *> &bsdfs, double lo, double hi) {
    if constexpr (is_spectral_v<Spectrum>)
        bsdfs.erase(std::remove_if(bsdfs.begin(), bsdfs.end(),
                                   [&](B *b) {
                                       fluo::Range ex = b->jit_excitation_range();
                                       return !(std::max(ex.lo, lo) < std::min(ex.hi, hi));
                                   }),
                    bsdfs.end());
    bool directional = false;
    for (B *b : bsdfs)
        directional |= !b->jit_lambertian();
    return directional;
}

/// Like Mitsuba's path, fluo_path does not trace participating media: say so once per
/// scene (`warned` remembers the last one) when a shape or sensor has one (a fluorescent
/// medium would otherwise render as empty space without a word).
template <typename Scene> void warn_if_media(const char *plugin, const Scene *scene, const Scene *&warned) {
    if (warned == scene)
        return;
    bool media = false;
    for (const auto &shape : scene->shapes())
        media |= shape->interior_medium() != nullptr || shape->exterior_medium() != nullptr;
    for (const auto &sensor : scene->sensors())
        media |= sensor->medium() != nullptr;
    if (!media)
        return;
    warned = scene;
    Log(Warn, "%s: the scene has participating media, which %s does not trace (as Mitsuba's path): "
              "they render as empty space. Use <integrator type=\"fluo_volpath\"/> for media, "
              "fluorescent (fluo_qd_medium, fluo_dye_medium) or not.", plugin, plugin);
}

/// Where the scene's light can start: the union of the wavelength ranges of the textures
/// of every emitter (Mitsuba's 360-830 nm for an emitter without one), nm; empty
/// (lo > hi) without emitters.
template <typename Float, typename Spectrum> fluo::Range emitters_range(const Scene<Float, Spectrum> *scene) {
    double lo = 1e30, hi = -1e30;
    for (const auto &emitter : scene->emitters()) {
        Collector c;
        c.visit(const_cast<Emitter<Float, Spectrum> *>(emitter.get()));
        bool found = false;
        for (Object *o : c.objects)
            if (auto *tex = dynamic_cast<Texture<Float, Spectrum> *>(o)) {
                auto r = tex->wavelength_range();
                lo = std::min(lo, (double) r.x());
                hi = std::max(hi, (double) r.y());
                found = true;
            }
        if (!found) {
            lo = std::min(lo, (double) MI_CIE_MIN);
            hi = std::max(hi, (double) MI_CIE_MAX);
        }
    }
    return fluo::Range{ lo, hi };
}

/// Direct children of an object as (name, object), in traverse order.
struct Children {
    std::vector<std::pair<std::string, Object *>> list;
    /// Scalar floating-point parameters by name (e.g. bumpmap's "scale").
    std::unordered_map<std::string, double> numbers;
    explicit Children(Object *obj) {
        auto value = [&](std::string_view name, void *ptr, const std::type_info &type) {
            if (type == typeid(float))
                numbers[std::string(name)] = *static_cast<const float *>(ptr);
            else if (type == typeid(double))
                numbers[std::string(name)] = *static_cast<const double *>(ptr);
        };
        visit(obj, value, [&](std::string_view name, Object *o) {
            if (o)
                list.emplace_back(std::string(name), o);
            return false;
        });
    }
};

/// The supported wrappers around fluorescent materials found in a scene, and their
/// resolution, per lane, to the child BSDF that acts at a vertex (fluo_path's docs).
template <typename Float, typename Spectrum> class FluoWrappers {
public:
    /// Errors and warnings read "[FluoPath] ...", as if raised by the integrator itself.
    static constexpr const char *ClassName = "FluoPath";
    MI_IMPORT_TYPES(BSDF, BSDFPtr, Sampler, Texture)
    using Bispectral = BispectralBSDF<Float, Spectrum>;

    /// Most wrappers nested around one material (each level may hold a normal or bump map).
    static constexpr size_t MaxDepth = 8;

    bool empty() const { return m_wrappers.empty(); }

    /// Record the wrappers around fluorescent materials among the scene's objects `c`;
    /// refuse wrappers it cannot see through (`plugin` names the integrator in the error).
    void scan(const Collector &c, const char *plugin) {
        m_wrappers.clear();
        for (Object *o : c.objects) {
            auto *bsdf = dynamic_cast<BSDF *>(o);
            if (!bsdf || dynamic_cast<Bispectral *>(o))
                continue;
            Children kids(o);
            bool wraps = false;
            for (auto &[name, child] : kids.list) {
                std::unordered_set<Object *> seen;
                wraps |= dynamic_cast<BSDF *>(child) && holds_fluorescence(child, seen);
            }
            if (!wraps)
                continue;
            std::string_view cls = o->class_name();
            if (cls != "TwoSidedBRDF" && cls != "BlendBSDF" && cls != "MaskBSDF" && cls != "NormalMap" &&
                cls != "BumpMap")
                Throw("%s: a fluorescent material is wrapped in a \"%s\" BSDF, which %s cannot "
                      "see through (its fluorescence would be lost). Supported wrappers: twosided, "
                      "blendbsdf, mask, normalmap, bumpmap; use the fluorescent material directly or "
                      "inside one of those.",
                      plugin, std::string(cls), plugin);
            Wrapper w{ bsdf, cls == "TwoSidedBRDF" ? Wrapper::TwoSided
                             : cls == "BlendBSDF"  ? Wrapper::Blend
                             : cls == "MaskBSDF"   ? Wrapper::Mask
                             : cls == "NormalMap"  ? Wrapper::NormalMap
                                                   : Wrapper::BumpMap };
            for (auto &[name, child] : kids.list) {
                auto *cb = dynamic_cast<BSDF *>(child);
                if (cb && (name == "brdf_0" || name == "bsdf_0" || name == "nested_bsdf"))
                    w.child[0] = cb;
                else if (cb && (name == "brdf_1" || name == "bsdf_1"))
                    w.child[1] = cb;
                else if (!cb && dynamic_cast<Texture *>(child) &&
                         (name == "weight" || name == "opacity" || name == "normalmap" || name == "nested_texture"))
                    w.weight = dynamic_cast<Texture *>(child);
            }
            if (auto it = kids.numbers.find("scale"); it != kids.numbers.end())
                w.scale = it->second;
            if (w.kind == Wrapper::TwoSided && !w.child[1])
                w.child[1] = w.child[0]; // one child: used on both sides
            if (w.kind == Wrapper::Mask)
                w.child[1] = null_bsdf();
            if (w.kind == Wrapper::NormalMap || w.kind == Wrapper::BumpMap)
                w.child[1] = w.child[0];
            if (!w.child[0] || !w.child[1] || (w.kind != Wrapper::TwoSided && !w.weight))
                Throw("%s: cannot read the children of the \"%s\" BSDF around a fluorescent material",
                      plugin, std::string(cls));
            m_wrappers.push_back(w);
        }
        m_depth = 0;
        for (const Wrapper &w : m_wrappers)
            m_depth = std::max(m_depth, depth(w.bsdf));
        if (m_depth > MaxDepth)
            Throw("%s: %zu BSDF wrappers (twosided, blendbsdf, mask, normalmap, bumpmap) nested around one "
                  "fluorescent material; at most %zu are supported",
                  plugin, m_depth, MaxDepth);
    }

    /// The shading normals a vertex's normal and bump maps replaced (each level's input and
    /// output normal, world space, and the lanes it applies to), for the adapters'
    /// orientation rule.
    struct Perturbations {
        Vector3f before[MaxDepth], after[MaxDepth];
        Mask applied[MaxDepth];
        size_t n = 0;
        /// Whether world direction d lies on the same side of each map's input and output
        /// shading normals: Mitsuba's normalmap and bumpmap give a direction that changes
        /// side (through the perturbed frame) no value, pdf or sample.
        Mask keeps_side(const Vector3f &d) const {
            Mask ok = true;
            for (size_t i = 0; i < n; ++i)
                ok &= !applied[i] || dr::dot(before[i], d) * dr::dot(after[i], d) > 0.f;
            return ok;
        }
    };

    /// The BSDF that acts at si, per lane: wrappers (twosided, blendbsdf, mask, normalmap,
    /// bumpmap; nested) resolved to the child acting at this hit, one nesting level at a
    /// time. For a twosided back side the local frame is mirrored (n -> -n), as twosided
    /// mirrors wi and wo; a normal or bump map replaces si's shading frame by the perturbed
    /// one (si.wi re-expressed in it), so the fluorescent vertex's every lobe uses it, and
    /// records both normals in `perturbed` (the caller drops directions that change side:
    /// Perturbations::keeps_side). blendbsdf and mask draw one number per level they occur in.
    BSDFPtr resolve(BSDFPtr bsdf, SurfaceInteraction3f &si, Sampler *sampler, Perturbations &perturbed,
                    Mask active) const {
        perturbed.n = 0;
        for (size_t level = 0; level < m_depth; ++level) {
            BSDFPtr next = bsdf;
            Frame3f mapped_frame = si.sh_frame;
            Mask mapped = false;
            for (const Wrapper &w : m_wrappers) {
                Mask on = active && (bsdf == BSDFPtr(w.bsdf));
                if (dr::none_or<false>(on))
                    continue;
                BSDFPtr c0(w.child[0]), c1(w.child[1]);
                if (w.kind == Wrapper::TwoSided) {
                    Mask back = on && Frame3f::cos_theta(si.wi) < 0.f;
                    dr::masked(si.sh_frame.n, back) = -si.sh_frame.n;
                    dr::masked(si.wi.z(), back) = -si.wi.z();
                    next = dr::select(on, dr::select(back, c1, c0), next);
                } else if (w.kind == Wrapper::Blend) {
                    Float weight = dr::clip(w.weight->eval_1(si, on), 0.f, 1.f);
                    next = dr::select(on, dr::select(sampler->next_1d(on) < weight, c1, c0), next);
                } else if (w.kind == Wrapper::Mask) {
                    Float opacity = dr::clip(w.weight->eval_1(si, on), 0.f, 1.f);
                    next = dr::select(on, dr::select(sampler->next_1d(on) < opacity, c0, c1), next);
                } else {
                    mapped_frame = dr::select(on, perturbed_frame(w, si, on), mapped_frame);
                    mapped |= on;
                    next = dr::select(on, c0, next);
                }
            }
            if (dr::any_or<true>(mapped)) {
                size_t i = perturbed.n++;
                perturbed.before[i] = si.sh_frame.n;
                perturbed.after[i] = mapped_frame.n;
                perturbed.applied[i] = mapped;
                Vector3f wi_world = si.sh_frame.to_world(si.wi);
                si.sh_frame = dr::select(mapped, mapped_frame, si.sh_frame);
                si.wi = dr::select(mapped, mapped_frame.to_local(wi_world), si.wi);
            }
            bsdf = next;
        }
        return bsdf;
    }

private:
    /// A supported BSDF wrapper around fluorescent materials.
    struct Wrapper {
        enum Kind { TwoSided, Blend, Mask, NormalMap, BumpMap };
        const BSDF *bsdf;
        Kind kind;
        const BSDF *child[2]{};          // front/back, bsdf_0/bsdf_1, nested/null, or nested twice
        const Texture *weight = nullptr; // blend weight, mask opacity, normal map or height map
        double scale = 1.0;              // bumpmap's height scale
    };

    /// Wrapper levels from `b` down to a material (0: not a wrapper).
    size_t depth(const BSDF *b) const {
        for (const Wrapper &w : m_wrappers)
            if (w.bsdf == b)
                return 1 + std::max(depth(w.child[0]), depth(w.child[1]));
        return 0;
    }

    /// The shading frame (world space) a normal or bump map gives at si, as Mitsuba's
    /// adapters build it: normalmap's normal n = 2·rgb − 1 in si's shading frame;
    /// bumpmap's normal of the surface displaced by scale·height along n (the height's
    /// uv gradient), turned to the geometric normal's side. The tangent follows dp/du
    /// (Gram-Schmidt); fluo's materials are isotropic, so only the normal matters.
    Frame3f perturbed_frame(const Wrapper &w, const SurfaceInteraction3f &si, const Mask &active) const {
        Vector3f n;
        if (w.kind == Wrapper::NormalMap) {
            n = si.sh_frame.to_world(dr::normalize(dr::fmadd(w.weight->eval_3(si, active), 2.f, -1.f)));
        } else {
            Vector2f grad = (Float) w.scale * w.weight->eval_1_grad(si, active);
            const Vector3f &sn = si.sh_frame.n;
            Vector3f dp_du = dr::fmadd(sn, grad.x() - dr::dot(sn, si.dp_du), si.dp_du);
            Vector3f dp_dv = dr::fmadd(sn, grad.y() - dr::dot(sn, si.dp_dv), si.dp_dv);
            n = dr::normalize(dr::cross(dp_du, dp_dv));
            n = dr::select(dr::dot(si.n, n) < 0.f, -n, n);
        }
        Vector3f t = dr::fnmadd(n, dr::dot(n, si.dp_du), si.dp_du);
        Frame3f f(n);
        Mask tangent = dr::squared_norm(t) > 1e-12f;
        f.s = dr::select(tangent, dr::normalize(t), f.s);
        f.t = dr::select(tangent, dr::cross(n, f.s), f.t);
        return f;
    }

    /// Whether `o` is, or has below it, a material that fluoresces.
    static bool holds_fluorescence(Object *o, std::unordered_set<Object *> &seen) {
        if (!o || !seen.insert(o).second)
            return false;
        if (auto *b = dynamic_cast<Bispectral *>(o); b && b->jit_fluorescent())
            return true;
        Children c(o);
        return std::any_of(c.list.begin(), c.list.end(),
                           [&](const auto &kid) { return holds_fluorescence(kid.second, seen); });
    }

    /// Mitsuba's `null` BSDF (pass-through, sampled as a Null/Delta event), created
    /// once: the transparent part of a `mask`.
    const BSDF *null_bsdf() {
        if (!m_null)
            m_null = PluginManager::instance()->create_object<BSDF>(Properties("null"));
        return m_null.get();
    }

    std::vector<Wrapper> m_wrappers;
    size_t m_depth = 0; ///< the longest chain of wrappers
    ref<BSDF> m_null;   ///< see null_bsdf()
};


/// Path replay (fluo_prb, fluo_prbvolpath): an emitter sample's weight (value over pdf,
/// `weight`) with the emitter's derivatives at the detached sample ds seen from `at`.
template <typename Scene, typename Interaction, typename DirectionSample, typename Spectrum, typename Mask>
Spectrum emitter_weight(const Scene *scene, const Interaction &at, const DirectionSample &ds, const Spectrum &weight,
                        const Mask &active) {
    Spectrum value = scene->eval_emitter_direction(at, ds, active);
    return with_grad(weight, value * dr::detach(dr::select(ds.pdf != 0.f, dr::rcp(ds.pdf), 0.f)));
}

/// The K coefficients s of a value linear in a 3×K block B (v = B·s): `value(P, b)` at
/// P = rows 3b, 3b + 1, 3b + 2 of the K×K identity (fewer where K ends), 3 coefficients a
/// call (⌈K/3⌉ calls): what continuations carry in place of a matrix throughput.
template <size_t K, typename Coeffs, typename Rows, typename Value> Coeffs probe_coefficients(Value &&value) {
    Coeffs s = dr::zeros<Coeffs>();
    for (size_t b = 0; 3 * b < K; ++b) {
        Rows probe = dr::zeros<Rows>();
        for (size_t r = 0; r < 3 && 3 * b + r < K; ++r)
            probe[r * K + 3 * b + r] = 1.f;
        auto v = value(probe, b);
        for (size_t r = 0; r < 3 && 3 * b + r < K; ++r)
            s[3 * b + r] = v[r];
    }
    return s;
}

/// The reduced transport's replay (fluo_prb, fluo_prbvolpath; K > 0): the radiance still
/// to come from the loop state `from`, per unit of throughput. A matrix throughput's is K
/// basis coefficients r (the path's rest R'·r), which its 3 RGB values do not determine; so
/// continuations of the path carry the identity's rows in place of R' (3 each, ⌈K/3⌉ of
/// them) and give r; an RGB throughput's is the 3 values of the first one (t = 1). Each
/// replays the path's random numbers (a clone of its sampler) without gradients, `run(state)`
/// being the integrator's loop (with its own roulette: unbiased, not the primal's decisions).
/// Memory does not grow with depth; time does, quadratically (each vertex continues the path
/// to its end). `weighed`: the lanes whose δL is not 0.
template <size_t K, typename Coeffs, typename Color3f, typename State, typename Mask, typename Run>
std::pair<Coeffs, Color3f> future(const State &from, const Mask &weighed, Run &&run) {
    using Float = dr::value_t<Color3f>;
    dr::suspend_grad<Float> detached;
    Color3f rgb = 0.f;
    Coeffs coeffs = probe_coefficients<K, Coeffs, decltype(from.c.R)>([&](const auto &probe, size_t b) {
        auto clone = from.sampler->clone();
        State cs = from;
        cs.sampler = clone.get();
        cs.result = dr::zeros<decltype(cs.result)>();
        cs.c.t = Color3f(1.f);
        cs.c.R = probe;
        if (b > 0) // RGB throughputs need the first only
            cs.active &= from.c.reduced;
        cs.active &= weighed;
        run(cs);
        if (b == 0)
            rgb = Color3f(cs.result);
        return Color3f(cs.result);
    });
    return { coeffs, rgb };
}

/// fluo_prb's and fluo_prbvolpath's reverse mode (Vicini et al. 2021, path replay
/// backpropagation, as Mitsuba's prb and prbvolpath): three passes of Mitsuba's render with
/// the same seed. (1) Every sample's radiance is a unit value with gradients:
/// backpropagating `grad_in` through the film (filter, spectrum to RGB, normalisation;
/// linear in the radiance) gives each sample's adjoint radiance δL. (2) The primal path: its
/// radiance L. (3) The same paths replayed (same random numbers, so the same vertices,
/// choices and wavelengths) carrying the radiance still to come; each vertex
/// backpropagates δL times what it contributes at once, inside the loop: memory does not
/// grow with depth. The integrator's sample() asks seed(), then replay().
template <typename Float, typename Spectrum> class PathReplay {
public:
    MI_IMPORT_TYPES(Sensor)

    /// The passes; `render(develop)` runs Mitsuba's SamplingIntegrator::render with the
    /// backward call's scene, sensor, seed and spp. `clipped`: the radiance is clipped at 0
    /// per sample (the reduced RGB transport), so a primal ≤ 0 gets no derivative (as
    /// dr::maximum's: none at 0).
    template <typename Render>
    void backward(const char *plugin, Render &&render, Sensor *sensor, const TensorXf &grad_in, uint32_t spp,
                  bool clipped) const {
        struct Reset { // the passes end with the integrator rendering again
            const PathReplay *self;
            ~Reset() {
                self->m_pass = Pass::Render;
                self->m_seed = self->m_primal = self->m_adjoint = Spectrum();
                self->m_valid = Bool();
            }
        } reset{ this };
        dr::suspend_grad<Float> detached;
        // one unit radiance per sample of the (single-pass) wavefront; only it carries
        // gradients through the film (not the sensor's or the film's own parameters)
        auto *film = sensor->film();
        ScalarVector2u size = film->crop_size();
        if (film->sample_border())
            size += 2 * film->rfilter()->border_size();
        m_seed = dr::full<Spectrum>(1.f, (size_t) size.x() * size.y() * (spp ? spp : sensor->sampler()->sample_count()));
        {
            dr::resume_grad<Float> attached;
            dr::enable_grad(m_seed);
        }
        {
            dr::resume_grad<Float> attached(true, m_seed);
            m_pass = Pass::Seed;
            TensorXf image = render(true);
            if (image.size() != grad_in.size())
                Throw("%s: the gradient image holds %zu values, the film develops %zu", plugin, grad_in.size(),
                      image.size());
            dr::set_grad(image.array(), grad_in.array());
            dr::enqueue(dr::ADMode::Backward, image.array());
            dr::traverse<Float>(dr::ADMode::Backward);
            m_adjoint = dr::grad(m_seed);
            m_seed = Spectrum();
        }
        // the primal loop stays symbolic: Dr.Jit traces it into the replay's kernel, so no
        // per-sample radiance is stored between the passes (as Mitsuba's prb)
        m_pass = Pass::Primal;
        render(false);
        m_adjoint = dr::select(m_valid, m_adjoint, 0.f);
        if (clipped)
            m_adjoint = dr::select(m_primal > 0.f, m_adjoint, 0.f);
        m_pass = Pass::Adjoint;
        render(false);
        dr::eval();
    }

    /// In sample(), first: pass 1's unit radiance (nothing in the other passes).
    std::optional<std::pair<Spectrum, Bool>> seed(const char *plugin, size_t width) const {
        if (m_pass != Pass::Seed)
            return std::nullopt;
        if (width != dr::width(m_seed))
            Throw("%s: the render runs in several passes (%zu samples per pass of %zu: \"samples_per_pass\", "
                  "or more than 2^32 samples); path replay needs one pass",
                  plugin, width, dr::width(m_seed));
        return std::make_pair(m_seed, Bool(true));
    }

    /// In sample(), passes 2 and 3: `trace(adjoint)` is the integrator's loop (its radiance
    /// kept in pass 2, the film receiving nothing of either); false in a render.
    template <typename Trace> bool replay(Trace &&trace) const {
        if (m_pass == Pass::Render || m_pass == Pass::Seed)
            return false;
        if (m_pass == Pass::Adjoint)
            trace(true);
        else
            std::tie(m_primal, m_valid) = trace(false);
        return true;
    }

    /// Pass 3: the primal radiance L and the adjoint radiance δL per sample.
    const Spectrum &primal() const { return m_primal; }
    const Spectrum &adjoint() const { return m_adjoint; }

private:
    enum class Pass { Render, Seed, Primal, Adjoint };
    mutable Pass m_pass = Pass::Render;
    mutable Spectrum m_seed, m_primal, m_adjoint; ///< unit radiance (pass 1), L (2), δL
    mutable Bool m_valid;
};

NAMESPACE_END(fluo_detail)
NAMESPACE_END(mitsuba)
