// Scene scanning for the fluo_path integrator: walking the scene graph, and the BSDF
// wrappers (twosided, blendbsdf, mask; nested too) that fluo_path sees through to the
// fluorescent material acting at a vertex. Shared by both transports
// (fluo_transport_spectral.h, fluo_transport_reduced.h); the path loop
// (fluo_path_loop.h) resolves the wrappers at each vertex.
#pragma once

#include <mitsuba/core/plugin.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/interaction.h>
#include <mitsuba/render/sampler.h>
#include <mitsuba/render/texture.h>

#include <algorithm>
#include <string>
#include <string_view>
#include <unordered_map>
#include <unordered_set>
#include <utility>
#include <vector>

#include "fluo_bispectral.h"

NAMESPACE_BEGIN(mitsuba)
NAMESPACE_BEGIN(fluo_detail)

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

/// The fluorescent BSDFs of the scene for a vectorised integrator (interface B, whose
/// jit_fluorescent() holds), refusing one inside a wrapper BSDF (twosided, blendbsdf, mask):
/// the vectorised loops cannot see through wrappers, and its fluorescence would be lost.
template <typename B, typename Scene> std::vector<B *> jit_fluorescent_bsdfs(const char *plugin, const Scene *scene) {
    std::unordered_set<const Object *> direct;
    Collector c;
    for (const auto &shape : scene->shapes()) {
        direct.insert(shape->bsdf());
        c.visit(const_cast<Object *>(static_cast<const Object *>(shape.get())));
    }
    std::vector<B *> out;
    for (Object *o : c.objects) {
        auto *b = dynamic_cast<B *>(o);
        if (!b || !b->jit_fluorescent())
            continue;
        if (!direct.count(o))
            Throw("%s: a fluorescent material is wrapped in another BSDF (twosided, blendbsdf, mask, ...), "
                  "which the vectorised variants cannot see through yet (its fluorescence would be lost): "
                  "use it directly, or render in scalar_spectral/scalar_rgb", plugin);
        out.push_back(b);
    }
    return out;
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
struct Children : TraversalCallback {
    std::vector<std::pair<std::string, Object *>> list;
    /// Scalar floating-point parameters by name (e.g. bumpmap's "scale").
    std::unordered_map<std::string, double> numbers;
    void put_value(std::string_view name, void *ptr, uint32_t, const std::type_info &type) override {
        if (type == typeid(float))
            numbers[std::string(name)] = *static_cast<const float *>(ptr);
        else if (type == typeid(double))
            numbers[std::string(name)] = *static_cast<const double *>(ptr);
    }
    void put_object(std::string_view name, Object *o, uint32_t) override {
        if (o)
            list.emplace_back(std::string(name), o);
    }
};

/// The supported wrappers around fluorescent materials found in a scene, and their
/// resolution at a vertex to the child BSDF that acts there (see fluo_path's docs).
template <typename Float, typename Spectrum> class FluoWrappers {
public:
    /// Errors and warnings read "[FluoPath] ...", as if raised by the integrator itself.
    static constexpr const char *ClassName = "FluoPath";
    MI_IMPORT_TYPES(BSDF, BSDFPtr, Sampler, Texture)

    bool empty() const { return m_wrappers.empty(); }
    void clear() { m_wrappers.clear(); }

    /// Mark every bispectral material among `c`'s objects as transported by fluo_path,
    /// and record the wrappers around fluorescent ones; refuse wrappers it cannot see
    /// through (`plugin` names the integrator in the error).
    void scan(const Collector &c, const char *plugin) {
        m_wrappers.clear();
        for (Object *o : c.objects) {
            if (auto *b = dynamic_cast<BispectralBSDF<Float, Spectrum> *>(o))
                b->set_managed(true);
            auto *bsdf = dynamic_cast<BSDF *>(o);
            if (!bsdf || dynamic_cast<BispectralBSDF<Float, Spectrum> *>(o))
                continue;
            Children kids;
            o->traverse(&kids);
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
                Throw("%s: a fluorescent material is wrapped in a \"%s\" BSDF, which fluo_path cannot "
                      "see through (its fluorescence would be lost). Supported wrappers: twosided, "
                      "blendbsdf, mask, normalmap, bumpmap; use the fluorescent material directly or "
                      "inside one of those.",
                      plugin, std::string(cls));
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
    }

    /// The shading normals a vertex's normal and bump maps replaced (each map's input and
    /// output normal, world space), for the adapters' orientation rule. Plain arrays,
    /// left uninitialised: every vertex declares one, most never fill it.
    struct Perturbations {
        static constexpr size_t Max = 8;
        Vector3f before[Max], after[Max];
        size_t n = 0;
        /// Whether world direction d lies on the same side of each map's input and output
        /// shading normals: Mitsuba's normalmap and bumpmap give a direction that changes
        /// side (through the perturbed frame) no value, pdf or sample.
        Mask keeps_side(const Vector3f &d) const {
            Mask ok = true;
            for (size_t i = 0; i < n; ++i)
                ok &= dr::dot(before[i], d) * dr::dot(after[i], d) > 0.f;
            return ok;
        }
    };

    /// The BSDF that acts at si: wrappers (twosided, blendbsdf, mask, normalmap, bumpmap;
    /// nested) resolved to the child acting at this hit. For a twosided back side the
    /// local frame is mirrored (n -> -n), as twosided mirrors wi and wo; a normal or bump
    /// map replaces si's shading frame by the perturbed one (si.wi re-expressed in it), so
    /// the fluorescent vertex's every lobe uses it, and records both frames in `perturbed`
    /// (the caller drops directions that change side: Perturbations::keeps_side).
    BSDFPtr resolve(BSDFPtr bsdf, SurfaceInteraction3f &si, Sampler *sampler, Perturbations &perturbed) const {
        perturbed.n = 0;
        for (size_t guard = 0; guard < 64; ++guard) {
            const Wrapper *w = nullptr;
            for (const Wrapper &x : m_wrappers)
                if (x.bsdf == bsdf)
                    w = &x;
            if (!w)
                return bsdf;
            if (w->kind == Wrapper::TwoSided) {
                bool back = Frame3f::cos_theta(si.wi) < 0.f;
                if (back) {
                    si.sh_frame.n = -si.sh_frame.n;
                    si.wi.z() = -si.wi.z();
                }
                bsdf = w->child[back ? 1 : 0];
            } else if (w->kind == Wrapper::Blend) {
                Float weight = dr::clip(w->weight->eval_1(si, true), 0.f, 1.f);
                bsdf = w->child[sampler->next_1d() < weight ? 1 : 0];
            } else if (w->kind == Wrapper::NormalMap || w->kind == Wrapper::BumpMap) {
                if (perturbed.n == Perturbations::Max)
                    Throw("more than %zu normal or bump maps nested around one fluorescent material",
                          Perturbations::Max);
                Frame3f before = si.sh_frame;
                si.sh_frame = perturbed_frame(*w, si);
                si.wi = si.sh_frame.to_local(before.to_world(si.wi));
                perturbed.before[perturbed.n] = before.n;
                perturbed.after[perturbed.n++] = si.sh_frame.n;
                bsdf = w->child[0];
            } else {
                Float opacity = dr::clip(w->weight->eval_1(si, true), 0.f, 1.f);
                bsdf = w->child[sampler->next_1d() < opacity ? 0 : 1];
            }
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

    /// The shading frame (world space) a normal or bump map gives at si, as Mitsuba's
    /// adapters build it: normalmap's normal n = 2·rgb − 1 in si's shading frame;
    /// bumpmap's normal of the surface displaced by scale·height along n (the height's
    /// uv gradient), turned to the geometric normal's side. The tangent follows dp/du
    /// (Gram-Schmidt); fluo's materials are isotropic, so only the normal matters.
    Frame3f perturbed_frame(const Wrapper &w, const SurfaceInteraction3f &si) const {
        Vector3f n;
        if (w.kind == Wrapper::NormalMap) {
            n = si.sh_frame.to_world(dr::normalize(dr::fmadd(w.weight->eval_3(si, true), 2.f, -1.f)));
        } else {
            Vector2f grad = (Float) w.scale * w.weight->eval_1_grad(si, true);
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
        if (auto *b = dynamic_cast<BispectralBSDF<Float, Spectrum> *>(o); b && b->fluorescence())
            return true;
        Children c;
        o->traverse(&c);
        for (auto &[name, child] : c.list)
            if (holds_fluorescence(child, seen))
                return true;
        return false;
    }

    /// Mitsuba's `null` BSDF (pass-through, sampled as a Null/Delta event), created
    /// once: the transparent part of a `mask`.
    const BSDF *null_bsdf() {
        if (!m_null)
            m_null = PluginManager::instance()->create_object<BSDF>(Properties("null"));
        return m_null.get();
    }

    std::vector<Wrapper> m_wrappers;
    ref<BSDF> m_null; ///< see null_bsdf()
};

/// The fluorescent BSDFs a transport found at prepare time (`Entry` has a `bsdf`
/// pointer), looked up per vertex by pointer in O(1): the cost of a vertex does not grow
/// with the number of fluorescent materials, and a scene without any pays one branch.
template <typename Entry> class EntryTable {
public:
    void clear() {
        m_entries.clear();
        m_keys.clear();
        m_index.clear();
    }
    /// Add an entry; a BSDF added twice keeps its first entry.
    void add(const Entry &e) {
        if (m_index.emplace(static_cast<const void *>(e.bsdf), m_entries.size()).second) {
            m_entries.push_back(e);
            m_keys.push_back(e.bsdf);
        }
    }
    const Entry *find(const void *bsdf) const {
        size_t n = m_keys.size();
        if (n <= LinearScanMax) { // a few materials: a scan beats hashing
            for (size_t i = 0; i < n; ++i)
                if (m_keys[i] == bsdf)
                    return &m_entries[i];
            return nullptr;
        }
        auto it = m_index.find(bsdf);
        return it == m_index.end() ? nullptr : &m_entries[it->second];
    }
    size_t size() const { return m_entries.size(); }
    bool empty() const { return m_entries.empty(); }

private:
    /// Up to this many entries, find() scans m_keys.
    static constexpr size_t LinearScanMax = 8;
    std::vector<Entry> m_entries;
    std::vector<const void *> m_keys; ///< m_entries[i].bsdf
    std::unordered_map<const void *, size_t> m_index;
};

NAMESPACE_END(fluo_detail)
NAMESPACE_END(mitsuba)
