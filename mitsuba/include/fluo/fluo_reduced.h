// The reduced RGB transport of fluo_path and fluo_volpath in the RGB variants (scalar_rgb,
// llvm_ad_rgb, cuda_ad_rgb): the transport basis and its constants, the scene's
// fluorescent BSDFs reduced once per render, the emitters' basis coefficients, and the
// per-lane products of a 3×K matrix throughput R with a vertex's operator. The estimator
// (fluo_path's docs): RGB throughput t until the first fluorescent event, then
// R = diag(t)·O, multiplied by K×K operators.
#pragma once

#include <mitsuba/core/properties.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/emitter.h>
#include <mitsuba/render/scene.h>

#include <algorithm>
#include <array>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include "fluo_common.h"
#include "fluo_bispectral.h"
#include "fluo_path_scene.h"

NAMESPACE_BEGIN(mitsuba)
NAMESPACE_BEGIN(fluo_detail)

template <typename Float, typename Spectrum> class ReducedTransport {
public:
    MI_IMPORT_TYPES(Scene, Emitter, EmitterPtr, BSDF, BSDFPtr)
    using Bispectral = BispectralBSDF<Float, Spectrum>;
    /// The transport is compiled for K = 3 (rgb), 4 (xyzu), 7 (x7; auto with one light band)
    /// and KMax (auto with two light bands).
    static constexpr size_t KMax = 8;
    template <size_t K> using Coeffs = dr::Array<Float, K>;
    template <size_t K> using Rows = dr::Array<Float, 3 * K>;

    /// The basis `basis` with reduction `method`; errors name `plugin`. `auto` is built for
    /// each render's lights in prepare() (x7's bands until then).
    ReducedTransport(const char *plugin, const std::string &basis, const std::string &method)
        : m_plugin(plugin), m_method(method), m_adaptive(basis == "auto") {
        set(rust_call(plugin, [&] { return fluo::transport_new(basis, method); }));
    }

    size_t bands() const { return m_k; }
    const fluo::TransportBasis &basis() const { return **m_transport; }
    std::string name() const { return std::string(fluo::transport_name(**m_transport)); }

    /// Once per render (RGB variants): reduce the fluorescent BSDFs `bsdfs` for the basis,
    /// find the emitters with a known spectrum and their coefficients, and warn once per
    /// scene of a mostly-UV one when anything fluoresces (`media`: fluorescent media).
    void prepare(const Scene *scene, const std::vector<Bispectral *> &bsdfs, bool media) {
        m_entries.clear();
        m_sources.clear();
        if constexpr (!is_rgb_v<Spectrum>) {
            (void) scene, (void) bsdfs, (void) media;
        } else {
            for (const auto &emitter : scene->emitters()) {
                Collector ce;
                ce.visit(const_cast<Emitter *>(emitter.get()));
                for (Object *o : ce.objects)
                    if (auto *src = dynamic_cast<SpectralSource *>(o); src && !m_sources.count(emitter.get()))
                        m_sources.emplace(emitter.get(), Source{ {}, src->rgb_luminance(), &src->illuminant() });
            }
            if (m_adaptive) { // the basis of these lights (each distinct spectrum once)
                rust::Vec<double> lights;
                std::unordered_set<const fluo::Illuminant *> seen;
                for (const auto &[emitter, src] : m_sources)
                    if (seen.insert(src.illuminant).second)
                        fluo::illuminant_on_grid(*src.illuminant, lights);
                set(rust_call(m_plugin, [&] {
                    return fluo::transport_adaptive(rust::Slice<const double>(lights.data(), lights.size()), m_method);
                }));
            }
            for (auto &[emitter, src] : m_sources) {
                src.coeffs.assign(m_k, 0.0);
                fluo::illuminant_coefficients(*src.illuminant, **m_transport,
                                              rust::Slice<double>(src.coeffs.data(), m_k));
            }
            for (Bispectral *b : bsdfs) {
                Entry e{ dynamic_cast<const BSDF *>(b), b };
                for (auto &m : e.m)
                    m.assign(m_k * m_k, 0.0);
                e.full = rust_call(m_plugin, [&] { return b->jit_reduced_matrices(**m_transport, e.m); });
                e.n_d = rust_call(m_plugin, [&] { return b->jit_reduced_derivatives(**m_transport, e.d); });
                std::vector<double> nodes;
                if (!b->jit_lambertian()) {
                    std::vector<double> dm;
                    size_t n_nodes = 0;
                    e.n_models = (uint32_t) rust_call(
                        m_plugin, [&] { return b->jit_reduced_nodes_table(**m_transport, dm, nodes, n_nodes); });
                    if (e.n_models > 0) {
                        e.n_nodes = (uint32_t) n_nodes;
                        e.models = load_floats<DynamicBuffer<Float>>(dm);
                    } else {
                        e.n_nodes = (uint32_t) rust_call(
                            m_plugin, [&] { return b->jit_reduced_nodes(**m_transport, e.m, nodes); });
                    }
                }
                if (e.n_nodes > 0 && e.n_models > 0) {
                    e.nodes = load_floats<DynamicBuffer<Float>>(nodes);
                } else if (e.n_nodes > 0) { // cell j's two nodes side by side (one 8-wide read)
                    constexpr size_t T = Bispectral::MaxTerms;
                    static_assert(T <= 4, "a cell holds two nodes of at most 4 terms");
                    std::vector<double> cells(8 * (e.n_nodes - 1), 0.0);
                    for (size_t j = 0; j + 1 < e.n_nodes; ++j)
                        for (size_t t = 0; t < T; ++t)
                            std::tie(cells[8 * j + t], cells[8 * j + 4 + t]) =
                                std::make_pair(nodes[j * T + t], nodes[(j + 1) * T + t]);
                    e.nodes = load_floats<DynamicBuffer<Float>>(cells);
                    e.nodes_host = std::move(nodes); // (gather_operators: a joined lobe's row)
                }
                // derivative matrices: K·K each, or per cosine node for a direction-dependent lobe
                size_t per = (e.n_nodes > 0 && e.n_models == 0 ? e.n_nodes : 1) * m_k * m_k;
                if (e.n_d != e.d.size() || (e.n_d > 0 && e.n_models > 0) ||
                    std::any_of(e.d.begin(), e.d.end(), [&](const std::vector<double> &d) { return d.size() != per; }))
                    Throw("%s: %s returned %zu derivative matrices (counted %zu), each of %zu entries expected", m_plugin,
                          e.bsdf->class_name(), e.d.size(), e.n_d, per);
                if (e.n_d > 0 && e.n_nodes > 0) { // [derivative][node][K][K], read per lane
                    std::vector<double> all;
                    for (const auto &d : e.d)
                        all.insert(all.end(), d.begin(), d.end());
                    e.node_d = load_floats<DynamicBuffer<Float>>(all);
                }
                std::vector<double> table;
                e.n_table = (uint32_t) rust_call(m_plugin, [&] { return b->jit_reduced_table(**m_transport, table); });
                if (e.n_table > 0) {
                    e.table = load_floats<DynamicBuffer<Float>>(table);
                    std::vector<double> td;
                    e.n_table_d = (uint32_t) rust_call(
                        m_plugin, [&] { return b->jit_reduced_table_derivatives(**m_transport, td); });
                    if (td.size() != (size_t) e.n_table_d * e.n_table * m_k * m_k)
                        Throw("%s: %s returned %zu derivative table entries, %u tables of %u operators expected",
                              m_plugin, e.bsdf->class_name(), td.size(), e.n_table_d, e.n_table);
                    if (e.n_table_d > 0)
                        e.table_d = load_floats<DynamicBuffer<Float>>(td);
                }
                for (size_t t = 0; t < Bispectral::MaxTerms; ++t) // (`m` as final: jit_reduced_nodes rewrites it)
                    for (size_t i = 0; i < e.m[t].size() && i < m_k * m_k; ++i)
                        e.mf[t][i / m_k * stride(m_k) + i % m_k] = (float) e.m[t][i];
                uniform_operator(e);
                m_entries.push_back(std::move(e));
            }
            // (gradients on baked parameters: their values change every optimisation step, and
            // literals would compile a kernel per step)
            m_opaque = m_entries.size() > LiteralEntries ||
                       std::any_of(m_entries.begin(), m_entries.end(), [](const Entry &e) { return e.n_d > 0; });
            gather_operators();
            opaque_operators();
            if ((!m_entries.empty() || media) && !m_adaptive && m_uv_warned != scene) {
                for (const auto &[emitter, src] : m_sources)
                    if (fluo::illuminant_is_mostly_uv(*src.illuminant)) {
                        warn_uv_emitter(m_plugin, "llvm_ad_rgb", emitter);
                        m_uv_warned = scene;
                        break;
                    }
            }
        }
    }

    /// The fluorescent BSDFs reduced for this render.
    size_t size() const { return m_entries.size(); }
    /// Whether one of them has a direction-dependent lobe that varies over the surface
    /// (vertex() then needs its number u).
    bool varying() const {
        return std::any_of(m_entries.begin(), m_entries.end(), [](const Entry &e) { return e.n_models > 0; });
    }

    /// diag(t)·O: the matrix throughput of a path whose RGB throughput is t.
    template <size_t K> Rows<K> output_rows(const Color3f &t) const {
        Rows<K> out;
        for (size_t r = 0; r < 3; ++r)
            for (size_t k = 0; k < K; ++k)
                out[r * K + k] = m_output[r * K + k] * t[r];
        return out;
    }

    /// Per-band albedo a_k = (F·v)_k / (F·1)_k of an RGB value: how a native
    /// (wavelength-preserving) BSDF, medium or phase weight acts on the K coefficients.
    template <size_t K> Coeffs<K> band_albedo(const Color3f &v) const {
        Coeffs<K> d;
        for (size_t k = 0; k < K; ++k)
            d[k] = band_albedo(k, v);
        return d;
    }
    /// Its band k.
    Float band_albedo(size_t k, const Color3f &v) const {
        const float *a = &m_albedo_map[3 * k];
        return a[0] * v[0] + a[1] * v[1] + a[2] * v[2];
    }

    /// Basis coefficients of an emitter's radiance `le` (RGB): a fluo_illuminant's own
    /// coefficients rescaled to the radiance's luminance, else F·le.
    template <size_t K> Coeffs<K> emitter_coefficients(const EmitterPtr &emitter, const Color3f &le,
                                                        const Mask &active) const {
        Coeffs<K> c;
        for (size_t k = 0; k < K; ++k)
            c[k] = m_from_rgb[3 * k] * le[0] + m_from_rgb[3 * k + 1] * le[1] + m_from_rgb[3 * k + 2] * le[2];
        // Emitters are compared by pointer (a handful per scene), without a virtual call.
        Float y = 0.212671f * le[0] + 0.715160f * le[1] + 0.072169f * le[2];
        for (const auto &[e, src] : m_sources) {
            Mask is_src = active && emitter == EmitterPtr(e);
            if (dr::none_or<false>(is_src))
                continue;
            Float s = src.luminance > 0.0 ? y * (float) (1.0 / src.luminance) : Float(0.f);
            for (size_t k = 0; k < K; ++k)
                c[k] = dr::select(is_src, s * (float) src.coeffs[k], c[k]);
        }
        return c;
    }

    /// Emitted radiance `le` of `emitter` reaching the camera through the path's throughput:
    /// R·c(le) in matrix form (`reduced`), else t·le.
    template <size_t K>
    Color3f through(const Rows<K> &R, const Color3f &t, const Mask &reduced, const EmitterPtr &emitter,
                    const Color3f &le, const Mask &active) const {
        return dr::select(reduced, apply<K>(R, emitter_coefficients<K>(emitter, le, active)), t * le);
    }

    /// The path's throughput after a vertex's BSDF sample (where `active`) of weight w: a
    /// fluorescent vertex (`is_fl`) gives R_fl = R·A(ωb)·cos/pdf (from vertex(), plus the
    /// BSDF's own elastic part where `native_elastic`) and switches the path to matrix form;
    /// a native one scales R's columns by w's band albedos, or t by w. `Rm`: the matrix
    /// throughput at the vertex (R, or diag(t)·O before the first fluorescent event).
    template <size_t K>
    void scatter(Rows<K> &R, Color3f &t, Mask &reduced, const Rows<K> &Rm, const Rows<K> &R_fl, const Mask &is_fl,
                 const Mask &native_elastic, const Color3f &w, const Mask &active) const {
        if constexpr (!dr::is_jit_v<Float>) { // (what the lane takes, only)
            if (!active)
                return;
            if (is_fl)
                R = native_elastic ? R_fl + scale_columns<K>(Rm, band_albedo<K>(w)) : R_fl;
            else if (reduced)
                R = scale_columns<K>(Rm, band_albedo<K>(w));
            else
                t *= w;
            reduced |= is_fl;
            return;
        }
        Rows<K> R_red = scale_columns<K>(Rm, band_albedo<K>(w));
        dr::masked(R, active) = dr::select(is_fl, R_fl + dr::select(native_elastic, R_red, 0.f),
                                           dr::select(reduced, R_red, R));
        dr::masked(t, active && !(reduced || is_fl)) *= w;
        reduced |= is_fl;
    }

    /// R·c (3×K times K).
    template <size_t K> static Color3f apply(const Rows<K> &R, const Coeffs<K> &c) {
        Color3f out;
        for (size_t r = 0; r < 3; ++r) {
            Float acc = R[r * K] * c[0];
#pragma GCC unroll 8
            for (size_t k = 1; k < K; ++k)
                acc = dr::fmadd(R[r * K + k], c[k], acc);
            out[r] = acc;
        }
        return out;
    }
    /// R·diag(d).
    template <size_t K> static Rows<K> scale_columns(Rows<K> R, const Coeffs<K> &d) {
        for (size_t r = 0; r < 3; ++r)
#pragma GCC unroll 8
            for (size_t j = 0; j < K; ++j)
                R[r * K + j] *= d[j];
        return R;
    }
    /// Per column k, the largest |R_rk| over the rows.
    template <size_t K> static Coeffs<K> column_max(const Rows<K> &R) {
        Coeffs<K> w;
        for (size_t k = 0; k < K; ++k)
            w[k] = dr::maximum(dr::maximum(dr::abs(R[k]), dr::abs(R[K + k])), dr::abs(R[2 * K + k]));
        return w;
    }
    /// The largest |R_rk|.
    template <size_t K> static Float max_abs(const Rows<K> &R) {
        Float m = dr::abs(R[0]);
        for (size_t i = 1; i < 3 * K; ++i)
            m = dr::maximum(m, dr::abs(R[i]));
        return m;
    }

    /// A fluorescent vertex for the emitter sample's direction `wa` and the sampled one
    /// `wb` (with pdf `pdf_b`), given the matrix throughput R. Returns where the BSDF is
    /// fluorescent, where its elastic part is the BSDF's own value (a direction-dependent
    /// lobe: the caller adds R·diag(band albedo of the BSDF's value) for it), the product
    /// towards wa (`Block`: the 3×K block R·A(ωa)·cos θa; else R·A(ωa)·cos θa·c, 3 values)
    /// and R·A(ωb)·cos θb/pdf_b. A = Σ w_t·M_t (+ the elastic band albedos when A lacks
    /// them) for a Lambertian material (f = A/π), lobe·w_0·Σ_t s_t(cos θ)·M_t for a
    /// direction-dependent one, which only scenes holding one (`directional`) ask for; u: a
    /// uniform number for a lobe that varies over the surface (one model of the hit's
    /// mixture picked per vertex; the caller draws it where varying() holds).
    template <size_t K, bool Block>
    auto vertex(const BSDFPtr &bsdf, const SurfaceInteraction3f &si, const Rows<K> &R, const Coeffs<K> &c,
                const Vector3f &wa, const Vector3f &wb, const Float &pdf_b, bool directional, const Float &u,
                const Mask &active) const {
        using Towards = std::conditional_t<Block, Rows<K>, Color3f>;
        auto towards = [](const Rows<K> &ra, const Coeffs<K> &c_, const Float &f) {
            if constexpr (Block) {
                (void) c_;
                return Towards(ra * f);
            } else {
                return Towards(apply<K>(ra, c_) * f);
            }
        };
        Float inv_pdf = dr::select(pdf_b > 0.f, dr::rcp(pdf_b), 0.f);
        // the operators formed once per render (gather_operators), read by registry id
        auto [g, RG] = gathered_product<K>(bsdf, R, active);
        Mask rest = active && !g;
        if (!directional) {
            auto [f, RA] = m_dispatch ? dispatch_any(
                bsdf,
                [this](const BSDF *b, const SurfaceInteraction3f &si_, const Rows<K> &R_, const Mask &on) {
                    const Entry *e = find(b);
                    return !e || e->gathered ? std::make_pair(Mask(false), dr::zeros<Rows<K>>())
                                             : std::make_pair(Mask(true), lambertian_product<K>(*e, si_, R_, on));
                },
                si, R, rest) : std::make_pair(Mask(false), dr::zeros<Rows<K>>());
            RA = dr::select(g, RG, RA);
            return std::make_tuple(Mask((f || g) && active), Mask(false), towards(RA, c, Bispectral::lambert(si, wa)),
                                   Rows<K>(RA * (Bispectral::lambert(si, wb) * inv_pdf)));
        }
        // joined direction-dependent lobes (gather_operators), per class, outside any call
        Mask jf = false;
        Towards va_j = dr::zeros<Towards>();
        Rows<K> rb_j = dr::zeros<Rows<K>>();
        if constexpr (dr::is_jit_v<Float>) {
            UInt32 id = dr::reinterpret_array<UInt32>(bsdf);
            for (const Lobes &l : m_lobes) {
                Mask known = rest && id < l.n_slots;
                UInt32 slot = fluo_detail::fetch<UInt32>(l.slots, id, known);
                Mask in = known && slot > 0u;
                auto [a, b] = joined_products<K, Block>(l, slot - 1u, si, R, c, wa, wb, in);
                va_j = dr::select(in, a, va_j);
                rb_j = dr::select(in, b, rb_j);
                jf |= in;
                rest &= !in;
            }
        }
        if (!m_dispatch) {
            Mask is_fl = (jf || g) && active;
            return std::make_tuple(is_fl, Mask(jf && active),
                                   dr::select(g, towards(RG, c, Bispectral::lambert(si, wa)), va_j),
                                   Rows<K>(dr::select(g, RG * Bispectral::lambert(si, wb), rb_j) * inv_pdf));
        }
        // Block = false: towards the emitter only R·A(ωa)·c leaves the call (3 values, not 3K).
        auto [f, native, va, rb] = dispatch_any(
            bsdf,
            [this, towards](const BSDF *b, const SurfaceInteraction3f &si_, const Rows<K> &R_, const Coeffs<K> &c_,
                            const Vector3f &wa_, const Vector3f &wb_, const Float &u_, const Mask &on) {
                const Entry *e = find(b);
                if (!e || e->gathered)
                    return std::make_tuple(Mask(false), Mask(false), dr::zeros<Towards>(), dr::zeros<Rows<K>>());
                if (e->n_nodes == 0) {
                    Rows<K> ra = lambertian_product<K>(*e, si_, R_, on);
                    return std::make_tuple(Mask(true), Mask(false), towards(ra, c_, Bispectral::lambert(si_, wa_)),
                                           Rows<K>(ra * Bispectral::lambert(si_, wb_)));
                }
                auto [va_, rb_] = e->n_models > 0 ? varying_products<K, Block>(*e, si_, R_, c_, wa_, wb_, u_, on)
                                                  : directional_products<K, Block>(*e, si_, R_, c_, wa_, wb_, on);
                return std::make_tuple(Mask(true), Mask(true), va_, rb_);
            },
            si, R, c, wa, wb, u, rest);
        Mask is_fl = (f || g || jf) && active;
        va = dr::select(jf, va_j, va);
        rb = dr::select(jf, rb_j, rb);
        return std::make_tuple(is_fl, Mask(((native && f) || jf) && active),
                               dr::select(g, towards(RG, c, Bispectral::lambert(si, wa)), va),
                               Rows<K>(dr::select(g, RG * Bispectral::lambert(si, wb), rb) * inv_pdf));
    }

private:
    /// Scenes with more fluorescent materials than this read their operators' entries as
    /// values of the kernel (dr::make_opaque) instead of literals: with literals, every
    /// material with its own operator compiled its own callable (200 distinct dyes: minutes);
    /// with few, literals keep the per-vertex cost (a constant multiply, zero entries skipped).
    static constexpr size_t LiteralEntries = ManyMaterials;

    /// A fluorescent BSDF and its reduced operator Σ w_i·M_i (f = M/π).
    struct Entry {
        const BSDF *bsdf;
        const Bispectral *bispectral;
        bool full = false; ///< the operator includes the elastic part
        bool gathered = false; ///< its operator is a row of m_rows (gather_operators)
        std::array<std::vector<double>, Bispectral::MaxTerms> m;
        std::array<std::vector<Float>, Bispectral::MaxTerms> mv; ///< `m` as opaque values (many materials)
        /// `m` in single precision (scalar variants: dense()), every term K rows of stride(K)
        std::array<std::array<float, KMax * KMax>, Bispectral::MaxTerms> mf{};
        /// Scalar variants, an operator the same at every hit: A itself (uniform_operator)
        std::array<float, KMax * KMax> a{};
        bool uniform = false;
        /// Derivative matrices of parameters baked into `m` (Bispectral::jit_reduced_derivatives)
        std::vector<std::vector<double>> d;
        std::vector<std::vector<Float>> dv; ///< `d` as opaque values (Lambertian)
        size_t n_d = 0;
        /// A direction-dependent lobe's derivative matrices at the cosine nodes
        /// ([n_d][n_nodes][K][K], per unit w_0, linear between the nodes)
        DynamicBuffer<Float> node_d;
        /// A direction-dependent lobe (Bispectral::jit_reduced_nodes): the terms' weights at
        /// the cosine nodes (the terms' matrices are `m`), per cell [n_nodes - 1][8]: its
        /// first node's MaxTerms weights, padding to 4, its second node's (nodes_host:
        /// [n_nodes][MaxTerms]). With models (n_models > 0): [model][n_nodes][MaxTerms].
        DynamicBuffer<Float> nodes;
        std::vector<double> nodes_host;
        uint32_t n_nodes = 0;
        /// A varying material (Bispectral::jit_reduced_table): its operators M_n, [n][K][K].
        DynamicBuffer<Float> table;
        uint32_t n_table = 0;
        /// Their derivatives (Bispectral::jit_reduced_table_derivatives): [d][n][K][K].
        DynamicBuffer<Float> table_d;
        uint32_t n_table_d = 0;
        /// A varying direction-dependent lobe (Bispectral::jit_reduced_nodes_table): every
        /// model's terms B_t ([model][MaxTerms][K][K]; `nodes` then [model][n_nodes][MaxTerms]),
        /// of which a lane reads the one it picks.
        DynamicBuffer<Float> models;
        uint32_t n_models = 0;
    };

    /// Many materials: the joinable direction-dependent lobes (Bispectral::jit_join) grouped
    /// by class and tag, each member's row [w_0, node weights [n_nodes][MaxTerms], terms'
    /// matrices [MaxTerms][K][K]] read per lane by the BSDF's registry id (joined_products).
    struct Lobes {
        const Bispectral *first; ///< evaluates the class's lobes (jit_lobe_joined)
        typename Bispectral::Joined joined;
        DynamicBuffer<Float> rows;
        DynamicBuffer<UInt32> slots; ///< registry id → 1 + member index (0: not a member)
        uint32_t n_slots, n_nodes, width;
    };

    /// A fluo_illuminant emitter's basis coefficients.
    struct Source {
        std::vector<double> coeffs;
        double luminance;
        const fluo::Illuminant *illuminant;
    };

    /// Entry i of term t of `e`'s operator: a literal, or (many materials) an opaque value.
    Float entry(const Entry &e, size_t t, size_t i) const {
        return m_opaque ? e.mv[t][i] : Float((float) e.m[t][i]);
    }
    /// Whether that entry is used: non-zero in `e` (literals) or in some material (opaque:
    /// every material then traces the same code).
    bool nonzero(const Entry &e, size_t t, size_t i) const {
        return m_opaque ? (bool) m_any[t][i] : e.m[t][i] != 0.0;
    }

    const Entry *find(const BSDF *b) const {
        auto it = std::find_if(m_entries.begin(), m_entries.end(), [b](const Entry &e) { return e.bsdf == b; });
        return it == m_entries.end() ? nullptr : &*it;
    }

    /// Scalar variants: Σ_t w_t·M_t as one dense K×K (row major) and R times it, branch free
    /// (the JIT path's per-entry zero tests, which keep literal kernels small, were most of a
    /// scalar vertex's cost at K = 7). Rows are padded to whole SSE packets (stride(): K = 7
    /// reads 8), the products' packets (times()).
    static constexpr size_t stride(size_t k) { return (k + 3) / 4 * 4; }
    template <size_t K> using Dense = std::array<float, K * stride(K)>;
    template <size_t K> static Dense<K> dense(const Entry &e, const std::array<Float, Bispectral::MaxTerms> &w) {
        Dense<K> a{};
        for (size_t t = 0; t < Bispectral::MaxTerms; ++t) {
            const float wt = w[t], *m = e.mf[t].data();
            for (size_t i = 0; i < K * stride(K); ++i)
                a[i] += wt * m[i];
        }
        return a;
    }
    /// Scalar variants: a Lambertian material whose operator is the same at every hit (no
    /// texture, table, cosine nodes or derivatives) has A = Σ_t w_t·M_t (+ the elastic band
    /// albedos where A lacks them) formed here, once per render, not at every vertex.
    void uniform_operator(Entry &e) const {
        if constexpr (!dr::is_jit_v<Float>) {
            e.uniform = e.bispectral->jit_uniform() && e.n_nodes == 0 && e.n_table == 0 && e.n_d == 0;
            if (!e.uniform)
                return;
            const std::array<Float, Bispectral::MaxTerms> w = e.bispectral->jit_reduced_weights();
            for (size_t t = 0; t < Bispectral::MaxTerms; ++t)
                for (size_t i = 0; i < m_k * stride(m_k); ++i)
                    e.a[i] += w[t] * e.mf[t][i];
            if (!e.full) {
                Color3f v = e.bispectral->jit_elastic_albedo(dr::zeros<SurfaceInteraction3f>(), true);
                for (size_t k = 0; k < m_k; ++k)
                    e.a[k * stride(m_k) + k] += band_albedo(k, v);
            }
        }
    }
    template <size_t K> static Rows<K> times(const Rows<K> &R, const Dense<K> &a) { return times<K>(R, a.data()); }
    /// (in packets of stride(K) floats, loops unrolled: indexed in a loop, Dr.Jit's 3K-array
    /// is a chain of branches; 2x faster at K = 7, measured)
    template <size_t K> static Rows<K> times(const Rows<K> &R, const float *a) {
        using Packet = dr::Array<float, stride(K)>;
        Packet acc[3] = { Packet(0.f), Packet(0.f), Packet(0.f) };
#pragma GCC unroll 8
        for (size_t k = 0; k < K; ++k) {
            Packet row = dr::load<Packet>(a + k * stride(K));
#pragma GCC unroll 3
            for (size_t i = 0; i < 3; ++i)
                acc[i] = dr::fmadd(Packet(R[i * K + k]), row, acc[i]);
        }
        Rows<K> out;
#pragma GCC unroll 3
        for (size_t i = 0; i < 3; ++i)
#pragma GCC unroll 8
            for (size_t j = 0; j < K; ++j)
                out[i * K + j] = acc[i][j];
        return out;
    }

    /// R·A where the lane's BSDF has its operator in m_rows (`g`), A read per lane at the
    /// row the BSDF's registry id maps to: no call, so no callable traced per material.
    template <size_t K> std::pair<Mask, Rows<K>> gathered_product(const BSDFPtr &bsdf, const Rows<K> &R,
                                                                   const Mask &active) const {
        if constexpr (!dr::is_jit_v<Float>) {
            (void) bsdf, (void) R, (void) active;
            return { Mask(false), Rows<K>() };
        } else {
            if (m_n_rows == 0)
                return { Mask(false), dr::zeros<Rows<K>>() };
            UInt32 id = dr::reinterpret_array<UInt32>(bsdf);
            Mask known = active && id < m_n_slots;
            UInt32 row = fluo_detail::fetch<UInt32>(m_slots, id, known);
            Mask g = known && row > 0u;
            UInt32 base = (row - 1u) * (uint32_t) (K * K);
            Rows<K> out = dr::zeros<Rows<K>>();
            for (size_t j = 0; j < K; ++j) {
                Coeffs<K> col; // A[:, j]
                for (size_t k = 0; k < K; ++k)
                    col[k] = fluo_detail::fetch<Float>(m_rows, base + (uint32_t) (k * K + j), g);
                Color3f rc = apply<K>(R, col);
                for (size_t r = 0; r < 3; ++r)
                    out[r * K + j] = rc[r];
            }
            return { g, out };
        }
    }

    /// The weights of `e`'s derivative matrices at a hit (Bispectral::jit_reduced_derivative_weights),
    /// one per matrix; none when it has none.
    std::vector<Float> derivative_weights(const Entry &e, const SurfaceInteraction3f &si, const Mask &on) const {
        if (e.n_d == 0)
            return {};
        std::vector<Float> wd = e.bispectral->jit_reduced_derivative_weights(si, on);
        if (wd.size() != e.n_d)
            Throw("%s: %zu derivative weights for %zu derivative matrices", m_plugin, wd.size(), e.n_d);
        return wd;
    }

    /// R·A for a Lambertian fluorescent vertex, A = Σ w_t·M_t (+ the elastic band albedos
    /// when A lacks them; + w·M_n of a varying material's table, gathered per lane, and its
    /// derivative tables' Σ_d w_d·D_{d,n}; the scalar variants, without AD, have none).
    template <size_t K>
    Rows<K> lambertian_product(const Entry &e, const SurfaceInteraction3f &si, const Rows<K> &R, const Mask &on) const {
        if constexpr (!dr::is_jit_v<Float>)
            if (e.uniform)
                return times<K>(R, e.a.data());
        Rows<K> ra;
        const std::array<Float, Bispectral::MaxTerms> w = e.bispectral->jit_reduced_weights();
        const bool elastic = !e.full;
        if constexpr (!dr::is_jit_v<Float>) {
            if (e.n_d == 0) {
                Dense<K> a = dense<K>(e, w);
                if (e.n_table > 0 && on) { // + w·M_n of the hit's operator
                    auto [n, weight] = e.bispectral->jit_reduced_select(si, on);
                    const float *m = e.table.data() + (size_t) n * K * K;
                    for (size_t i = 0; i < K * K; ++i)
                        a[i / K * stride(K) + i % K] += weight * m[i];
                }
                if (elastic) {
                    Coeffs<K> d = band_albedo<K>(e.bispectral->jit_elastic_albedo(si, on));
                    for (size_t k = 0; k < K; ++k)
                        a[k * stride(K) + k] += d[k];
                }
                return times<K>(R, a);
            }
        }
        // A is formed one column at a time (the M_t are the material's constants): K·K values
        // of A never live at once, which at K = 7 spilled registers (a third of the render time).
        Coeffs<K> d = dr::zeros<Coeffs<K>>();
        if (elastic)
            d = band_albedo<K>(e.bispectral->jit_elastic_albedo(si, on));
        std::vector<Float> wd = derivative_weights(e, si, on);
        UInt32 base(0);
        Float wn(0.f);
        std::vector<Float> wt; // (the table's derivatives: their weights)
        if (e.n_table > 0) {
            auto [n, weight] = e.bispectral->jit_reduced_select(si, on);
            base = n * (uint32_t) (K * K);
            wn = weight;
            if (e.n_table_d > 0) {
                wt = e.bispectral->jit_reduced_select_derivatives(si, on);
                if (wt.size() != e.n_table_d)
                    Throw("%s: %zu derivative weights for %u derivative tables", m_plugin, wt.size(), e.n_table_d);
            }
        }
        for (size_t j = 0; j < K; ++j) {
            Coeffs<K> col = dr::zeros<Coeffs<K>>(); // A[:, j]
            for (size_t k = 0; k < K; ++k) {
                if (e.n_table > 0)
                    col[k] = wn * fluo_detail::fetch<Float>(e.table, base + (uint32_t) (k * K + j), on);
                for (uint32_t t = 0; t < (uint32_t) wt.size(); ++t)
                    col[k] = dr::fmadd(wt[t],
                                       fluo_detail::fetch<Float>(e.table_d, base + t * e.n_table * (uint32_t) (K * K) +
                                                                       (uint32_t) (k * K + j), on),
                                       col[k]);
                for (size_t t = 0; t < Bispectral::MaxTerms; ++t)
                    if (nonzero(e, t, k * K + j))
                        col[k] = dr::fmadd(w[t], entry(e, t, k * K + j), col[k]);
                for (size_t t = 0; t < e.n_d; ++t)
                    if (e.d[t][k * K + j] != 0.0)
                        col[k] = dr::fmadd(wd[t], e.dv[t][k * K + j], col[k]);
                if (elastic && k == j)
                    col[k] += d[k];
            }
            Color3f rc = apply<K>(R, col);
            for (size_t r = 0; r < 3; ++r)
                ra[r * K + j] = rc[r];
        }
        return ra;
    }

    /// For a direction-dependent lobe, R·A(ωo)·cos θo towards wa (`Block`: the 3×K block;
    /// else times the emitter sample's coefficients c) and towards wb:
    /// lobe·w_0·R·Σ_t s_t(cos θ)·M_t, the s_t linear between the entry's nodes
    /// (Bispectral::jit_reduced_nodes, jit_lobe). Each R·M_t column serves both directions.
    template <size_t K, bool Block>
    auto directional_products(const Entry &e, const SurfaceInteraction3f &si, const Rows<K> &R, const Coeffs<K> &c,
                              const Vector3f &wa, const Vector3f &wb, const Mask &on) const {
        constexpr uint32_t T = (uint32_t) Bispectral::MaxTerms;
        using Weights = std::array<Float, Bispectral::MaxTerms>;
        const Float w0 = e.bispectral->jit_reduced_weights()[0];
        auto weights = [&](const Vector3f &wo) {
            auto [lobe, cos_h] = e.bispectral->jit_lobe(si, wo, on);
            Float scale = lobe * w0;
            Float x = dr::clip(cos_h, 0.f, 1.f) * (float) (e.n_nodes - 1);
            UInt32 j = dr::minimum(UInt32(dr::floor(x)), e.n_nodes - 2);
            Float f = x - Float(j);
            Mask live = on && lobe != 0.f;
            auto cell = fluo_detail::fetch_packet<8, 4 + T, Float>(e.nodes, j, live); // (both nodes at once)
            Weights w;
            for (uint32_t t = 0; t < T; ++t)
                w[t] = dr::lerp(cell[t], cell[4 + t], f) * scale;
            return w;
        };
        Weights w_a = weights(wa), w_b = weights(wb);
        if constexpr (!dr::is_jit_v<Float>) {
            if (e.n_d == 0) {
                Dense<K> a = dense<K>(e, w_a);
                // (towards the emitter (R·A(ωa))·c: the product vectorises, A(ωa)·c's rows would not)
                if constexpr (Block)
                    return std::make_pair(times<K>(R, a), times<K>(R, dense<K>(e, w_b)));
                else
                    return std::make_pair(apply<K>(times<K>(R, a), c), times<K>(R, dense<K>(e, w_b)));
            }
        }
        std::conditional_t<Block, Rows<K>, Color3f> out_a = dr::zeros<std::conditional_t<Block, Rows<K>, Color3f>>();
        Rows<K> out_b = dr::zeros<Rows<K>>();
        if (e.n_d > 0) // parameters baked into the nodes with gradients: Σ_d wd_d·lobe·w_0·R·∂M/∂θ_d(cos θ)
            node_derivatives<K, Block>(e, si, R, c, wa, wb, on, out_a, out_b);
        for (size_t t = 0; t < Bispectral::MaxTerms; ++t)
            for (size_t j = 0; j < K; ++j) {
                Float wc = Block ? w_a[t] : w_a[t] * c[j];
                for (size_t r = 0; r < 3; ++r) {
                    Float acc = 0.f; // (R·M_t)[r, j]
                    bool any = false;
                    for (size_t k = 0; k < K; ++k)
                        if (nonzero(e, t, k * K + j)) {
                            Float m = entry(e, t, k * K + j);
                            acc = any ? dr::fmadd(R[r * K + k], m, acc) : R[r * K + k] * m;
                            any = true;
                        }
                    if (!any)
                        continue;
                    if constexpr (Block)
                        out_a[r * K + j] = dr::fmadd(wc, acc, out_a[r * K + j]);
                    else
                        out_a[r] = dr::fmadd(wc, acc, out_a[r]);
                    out_b[r * K + j] = dr::fmadd(w_b[t], acc, out_b[r * K + j]);
                }
            }
        return std::make_pair(out_a, out_b);
    }

    /// directional_products of joined materials (gather_operators): the lane's member's
    /// weight w_0, node weights and terms' matrices read from its class's rows, its lobe from
    /// the class (Bispectral::jit_lobe_joined).
    template <size_t K, bool Block>
    auto joined_products(const Lobes &l, const UInt32 &member, const SurfaceInteraction3f &si, const Rows<K> &R,
                         const Coeffs<K> &c, const Vector3f &wa, const Vector3f &wb, const Mask &on) const {
        UInt32 base = member * l.width;
        return table_products<K, Block>(
            l.rows, base + 1u, l.rows, base + 1u + l.n_nodes * (uint32_t) Bispectral::MaxTerms, l.n_nodes,
            fluo_detail::fetch<Float>(l.rows, base, on),
            [&](const Vector3f &wo, const Mask &m) { return l.first->jit_lobe_joined(l.joined, member, si, wo, m); },
            R, c, wa, wb, on);
    }

    /// The derivative terms of directional_products (Bispectral::jit_reduced_derivatives of a
    /// direction-dependent lobe): per derivative d, wd_d·lobe·w_0·R·D_d(cos θ) towards wa
    /// (times c unless `Block`) and wb, D_d linear between the nodes as the operator is;
    /// zero in value (wd_d = θ_d − detach(θ_d)), so only the derivative along θ_d remains.
    template <size_t K, bool Block, typename OutA>
    void node_derivatives(const Entry &e, const SurfaceInteraction3f &si, const Rows<K> &R, const Coeffs<K> &c,
                          const Vector3f &wa, const Vector3f &wb, const Mask &on, OutA &out_a, Rows<K> &out_b) const {
        constexpr uint32_t KK = (uint32_t) (K * K);
        std::vector<Float> wd = derivative_weights(e, si, on);
        Float w0 = e.bispectral->jit_reduced_weights()[0];
        for (int side = 0; side < 2; ++side) {
            auto [lobe, cos_h] = e.bispectral->jit_lobe(si, side == 0 ? wa : wb, on);
            Float x = dr::clip(cos_h, 0.f, 1.f) * (float) (e.n_nodes - 1);
            UInt32 j = dr::minimum(UInt32(dr::floor(x)), e.n_nodes - 2);
            Float f = x - Float(j);
            Mask live = on && lobe != 0.f;
            for (size_t d = 0; d < e.n_d; ++d) {
                Float scale = wd[d] * lobe * w0;
                UInt32 base = ((uint32_t) d * e.n_nodes + j) * KK;
                for (size_t col = 0; col < K; ++col) {
                    Coeffs<K> m; // ∂A/∂θ_d [:, col] at cos θ
                    for (size_t k = 0; k < K; ++k) {
                        uint32_t i = (uint32_t) (k * K + col);
                        m[k] = dr::lerp(fluo_detail::fetch<Float>(e.node_d, base + i, live),
                                        fluo_detail::fetch<Float>(e.node_d, base + KK + i, live), f) * scale;
                    }
                    Color3f acc = apply<K>(R, m);
                    for (size_t r = 0; r < 3; ++r) {
                        if (side == 1)
                            out_b[r * K + col] += acc[r];
                        else if constexpr (Block)
                            out_a[r * K + col] += acc[r];
                        else
                            out_a[r] = dr::fmadd(acc[r], c[col], out_a[r]);
                    }
                }
            }
        }
    }

    /// directional_products for a lobe that varies over the surface: per lane the model m and
    /// weight w that Bispectral::jit_reduced_pick draws with u, the operator lobe·w·Σ_t
    /// s_t^m(cos θ)·B_t^m.
    template <size_t K, bool Block>
    auto varying_products(const Entry &e, const SurfaceInteraction3f &si, const Rows<K> &R, const Coeffs<K> &c,
                          const Vector3f &wa, const Vector3f &wb, const Float &u, const Mask &on) const {
        constexpr uint32_t T = (uint32_t) Bispectral::MaxTerms, KK = (uint32_t) (K * K);
        auto [model, weight] = e.bispectral->jit_reduced_pick(si, u, on);
        return table_products<K, Block>(
            e.nodes, model * e.n_nodes * T, e.models, model * (T * KK), e.n_nodes, weight,
            [&](const Vector3f &wo, const Mask &m) { return e.bispectral->jit_lobe(si, wo, m); }, R, c, wa, wb,
            on && weight > 0.f);
    }

    /// lobe·scale·R·Σ_t s_t(cos θ)·B_t towards wa (`Block`: the 3×K block; else times the
    /// emitter sample's coefficients c) and towards wb, per lane: the terms' weights s_t
    /// linear between n_nodes cosine nodes ([n_nodes][MaxTerms] in `nodes` from node_base),
    /// the terms B_t ([MaxTerms][K][K] in `terms` from term_base), the lobe and cos θ from
    /// lobe_of(ωo, mask). The operator's columns are formed one at a time from the gathered
    /// B_t (each gather serves both directions).
    template <size_t K, bool Block, typename LobeOf>
    auto table_products(const DynamicBuffer<Float> &nodes, const UInt32 &node_base, const DynamicBuffer<Float> &terms,
                        const UInt32 &term_base, uint32_t n_nodes, const Float &scale, const LobeOf &lobe_of,
                        const Rows<K> &R, const Coeffs<K> &c, const Vector3f &wa, const Vector3f &wb,
                        const Mask &live) const {
        constexpr uint32_t T = (uint32_t) Bispectral::MaxTerms, KK = (uint32_t) (K * K);
        using Weights = std::array<Float, T>;
        auto weights = [&](const Vector3f &wo) {
            auto [lobe, cos_h] = lobe_of(wo, live);
            Float x = dr::clip(cos_h, 0.f, 1.f) * (float) (n_nodes - 1);
            UInt32 j = dr::minimum(UInt32(dr::floor(x)), n_nodes - 2);
            Float f = x - Float(j);
            Mask m = live && lobe != 0.f;
            UInt32 row = node_base + j * T;
            Weights w;
            for (uint32_t t = 0; t < T; ++t)
                w[t] = dr::lerp(fluo_detail::fetch<Float>(nodes, row + t, m), fluo_detail::fetch<Float>(nodes, row + T + t, m), f) *
                       (lobe * scale);
            return w;
        };
        Weights w_a = weights(wa), w_b = weights(wb);
        std::conditional_t<Block, Rows<K>, Color3f> out_a = dr::zeros<std::conditional_t<Block, Rows<K>, Color3f>>();
        Rows<K> out_b;
        for (size_t j = 0; j < K; ++j) {
            Coeffs<K> col_a = dr::zeros<Coeffs<K>>(), col_b = dr::zeros<Coeffs<K>>(); // A[:, j]
            for (size_t k = 0; k < K; ++k)
                for (uint32_t t = 0; t < T; ++t) {
                    Float b = fluo_detail::fetch<Float>(terms, term_base + (t * KK + (uint32_t) (k * K + j)), live);
                    col_a[k] = dr::fmadd(w_a[t], b, col_a[k]);
                    col_b[k] = dr::fmadd(w_b[t], b, col_b[k]);
                }
            Color3f acc_a = apply<K>(R, col_a), acc_b = apply<K>(R, col_b);
            for (size_t r = 0; r < 3; ++r) {
                if constexpr (Block)
                    out_a[r * K + j] = acc_a[r];
                else
                    out_a[r] = dr::fmadd(acc_a[r], c[j], out_a[r]);
                out_b[r * K + j] = acc_b[r];
            }
        }
        return std::make_pair(out_a, out_b);
    }

    void check_bands() const {
        if (m_k != 3 && m_k != 4 && m_k != 7 && m_k != KMax)
            Throw("%s: basis \"%s\" has %zu bands; the transport is compiled for 3, 4, 7 and %zu", m_plugin,
                  name(), m_k, KMax);
    }

    /// The transport `t`, its size and RGB maps.
    void set(rust::Box<fluo::TransportBasis> t) {
        m_transport = std::move(t);
        m_k = fluo::transport_size(**m_transport);
        check_bands();
        std::vector<double> output(3 * m_k), from_rgb(3 * m_k), white(m_k);
        fluo::transport_output(**m_transport, rust::Slice<double>(output.data(), output.size()));
        fluo::transport_from_rgb(**m_transport, rust::Slice<double>(from_rgb.data(), from_rgb.size()));
        fluo::transport_white(**m_transport, rust::Slice<double>(white.data(), white.size()));
        m_output.assign(output.begin(), output.end());
        m_from_rgb.assign(from_rgb.begin(), from_rgb.end());
        // band_albedo's rows: F_k/(F·1)_k, or the mean where a band holds no white
        m_albedo_map.resize(3 * m_k);
        for (size_t k = 0; k < m_k; ++k)
            for (size_t c = 0; c < 3; ++c)
                m_albedo_map[3 * k + c] = std::abs(white[k]) > 1e-12 ? (float) (from_rgb[3 * k + c] / white[k]) : 1.f / 3.f;
    }

    const char *m_plugin;
    std::string m_method;
    bool m_adaptive; ///< basis "auto": built in prepare() from the scene's light spectra
    std::optional<rust::Box<fluo::TransportBasis>> m_transport;
    size_t m_k = 3;
    std::vector<float> m_output, m_from_rgb; ///< O (3×K) and F (K×3), in single precision
    std::vector<float> m_albedo_map;         ///< band_albedo's K×3 map
    std::vector<Entry> m_entries;
    bool m_opaque = false; ///< see LiteralEntries
    std::array<std::vector<bool>, Bispectral::MaxTerms> m_any; ///< per term: entries non-zero in some material

    /// The entries' kernel inputs (m_opaque), for the materials gather_operators left to a call.
    void opaque_operators() {
        for (Entry &e : m_entries) {
            e.dv.resize(e.n_nodes > 0 ? 0 : e.n_d);
            for (size_t t = 0; t < e.dv.size(); ++t) {
                e.dv[t].resize(e.d[t].size());
                for (size_t i = 0; i < e.d[t].size(); ++i)
                    if (e.d[t][i] != 0.0) { // (only these are read: lambertian_product)
                        e.dv[t][i] = Float((float) e.d[t][i]);
                        dr::make_opaque(e.dv[t][i]);
                    }
            }
        }
        if (!m_opaque)
            return;
        for (size_t t = 0; t < Bispectral::MaxTerms; ++t) {
            m_any[t].assign(m_k * m_k, false);
            for (const Entry &e : m_entries)
                for (size_t i = 0; i < e.m[t].size() && i < m_any[t].size(); ++i)
                    m_any[t][i] = m_any[t][i] || e.m[t][i] != 0.0;
        }
        for (Entry &e : m_entries)
            for (size_t t = 0; t < Bispectral::MaxTerms; ++t) {
                // (a gathered material's operator is read from gather_operators' table: 200
                // coatings spent ~0.1 s on 29,400 opaque entries no lane read)
                e.mv[t].resize(e.gathered ? 0 : e.m[t].size());
                for (size_t i = 0; i < e.mv[t].size(); ++i) {
                    e.mv[t][i] = Float((float) e.m[t][i]);
                    dr::make_opaque(e.mv[t][i]);
                }
            }
    }
    /// Many materials (JIT variants, m_opaque): each Lambertian material whose operator is
    /// the same at every hit and carries no gradient has A = Σ_t w_t·M_t (+ the elastic band
    /// albedos where A lacks them) formed here, once per render, as a row of one table that
    /// vertex() reads per lane through the BSDF's registry id, outside any call. Dr.Jit
    /// traces and assembles a dispatch once per instance: 200 distinct dyes spent most of
    /// their first render doing so for this product.
    void gather_operators() {
        m_n_rows = m_n_slots = 0;
        m_dispatch = !m_entries.empty();
        m_lobes.clear();
        for (Entry &e : m_entries)
            e.gathered = false;
        if constexpr (dr::is_jit_v<Float> && is_rgb_v<Spectrum>) {
            if (!m_opaque)
                return;
            const size_t kk = m_k * m_k;
            std::vector<float> rows;
            std::vector<uint32_t> slots;
            m_dispatch = false;
            join_lobes();
            for (Entry &e : m_entries) {
                if (e.gathered) // (a joined lobe)
                    continue;
                auto w = e.bispectral->jit_reduced_weights();
                Color3f el(0.f);
                bool plain = e.bispectral->jit_uniform() && e.n_nodes == 0 && e.n_table == 0 && e.n_d == 0 &&
                             std::none_of(w.begin(), w.end(), [](const Float &x) { return dr::grad_enabled(x); });
                if (plain && !e.full) {
                    el = e.bispectral->jit_elastic_albedo(dr::zeros<SurfaceInteraction3f>(), Mask(true));
                    plain = !dr::grad_enabled(el);
                }
                uint32_t id = plain ? jit_registry_id(e.bsdf) : 0u;
                if (id == 0) {
                    m_dispatch = true;
                    continue;
                }
                e.gathered = true;
                if (slots.size() <= id)
                    slots.resize(id + 1, 0u);
                slots[id] = (uint32_t) (rows.size() / kk) + 1u;
                float wt[Bispectral::MaxTerms], e3[3];
                for (size_t t = 0; t < Bispectral::MaxTerms; ++t)
                    wt[t] = dr::slice(w[t]);
                for (size_t c = 0; c < 3; ++c)
                    e3[c] = dr::slice(el[c]);
                for (size_t i = 0; i < kk; ++i) {
                    double a = 0.0;
                    for (size_t t = 0; t < Bispectral::MaxTerms; ++t)
                        if (i < e.m[t].size())
                            a += wt[t] * e.m[t][i];
                    if (!e.full && i % (m_k + 1) == 0) { // the diagonal: band k's elastic albedo
                        const float *map = &m_albedo_map[3 * (i / m_k)];
                        a += map[0] * e3[0] + map[1] * e3[1] + map[2] * e3[2];
                    }
                    rows.push_back((float) a);
                }
            }
            if (rows.empty())
                return;
            m_n_rows = rows.size() / kk;
            m_n_slots = (uint32_t) slots.size();
            m_rows = dr::load<DynamicBuffer<Float>>(rows.data(), rows.size());
            m_slots = dr::load<DynamicBuffer<UInt32>>(slots.data(), slots.size());
        }
    }
    std::vector<Lobes> m_lobes;
    void join_lobes() {
        std::vector<Entry *> entries;
        std::vector<const Bispectral *> materials;
        std::vector<uint32_t> ids;
        std::vector<std::string> keys; // (one node count per class's rows)
        for (Entry &e : m_entries) {
            uint32_t id = jit_registry_id(e.bsdf);
            if (id == 0 || e.n_nodes < 2 || e.n_models > 0 || e.n_table > 0 || e.n_d > 0 ||
                e.nodes_host.size() != (size_t) e.n_nodes * Bispectral::MaxTerms || !e.bispectral->jit_joinable() ||
                dr::grad_enabled(e.bispectral->jit_reduced_weights()[0]))
                continue;
            entries.push_back(&e);
            materials.push_back(e.bispectral);
            ids.push_back(id);
            keys.push_back(std::to_string(e.n_nodes));
        }
        const size_t kk = m_k * m_k, T = Bispectral::MaxTerms;
        for (auto &g : join_classes(materials, ids, keys)) {
            uint32_t n_nodes = entries[g.members.front()]->n_nodes, width = (uint32_t) (1 + n_nodes * T + T * kk);
            std::vector<float> rows;
            for (size_t i : g.members) {
                Entry &e = *entries[i];
                rows.push_back(dr::slice(dr::detach(e.bispectral->jit_reduced_weights()[0])));
                rows.insert(rows.end(), e.nodes_host.begin(), e.nodes_host.end());
                for (size_t t = 0; t < T; ++t)
                    for (size_t j = 0; j < kk; ++j)
                        rows.push_back(j < e.m[t].size() ? (float) e.m[t][j] : 0.f);
                e.gathered = true;
            }
            m_lobes.push_back(Lobes{ materials[g.members.front()], std::move(g.joined),
                                     dr::load<DynamicBuffer<Float>>(rows.data(), rows.size()),
                                     dr::load<DynamicBuffer<UInt32>>(g.slots.data(), g.slots.size()),
                                     (uint32_t) g.slots.size(), n_nodes, width });
        }
    }
    DynamicBuffer<Float> m_rows;    ///< gathered operators, [row][K][K]
    DynamicBuffer<UInt32> m_slots;  ///< BSDF registry id → 1 + its row (0: none)
    size_t m_n_rows = 0;
    uint32_t m_n_slots = 0;
    bool m_dispatch = true; ///< some fluorescent material is reached through a call

    std::unordered_map<const Emitter *, Source> m_sources;
    const Scene *m_uv_warned = nullptr; ///< the scene last warned of a UV emitter
};

NAMESPACE_END(fluo_detail)
NAMESPACE_END(mitsuba)
