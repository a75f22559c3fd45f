// fluo_path's reduced-RGB transport (scalar_rgb with fluorescent materials): matrix
// throughput in a K-band transport basis (Fichet et al. 2024, sec. 5.1, adjoint
// transport; fluo_path's docs describe it). A path carries Mitsuba's RGB throughput t
// until its first fluorescent vertex, which turns it into the 3×K matrix
// R = diag(t)·O·M; later vertices multiply R by K×K matrices. The basis and the
// reduced operators come from the Rust core (core/src/reduce/) through the bridge. It
// plugs into FluoPathLoop (fluo_path_loop.h) as its `Path`.
#pragma once

#include <mitsuba/core/logger.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/emitter.h>
#include <mitsuba/render/scene.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <string>
#include <type_traits>
#include <vector>

#include "fluo_bispectral.h"
#include "fluo_common.h"
#include "fluo_path_loop.h"
#include "fluo_path_scene.h"

NAMESPACE_BEGIN(mitsuba)

template <typename Float, typename Spectrum> class ReducedTransport {
public:
    /// Errors and warnings read "[FluoPath] ...", as if raised by the integrator itself.
    static constexpr const char *ClassName = "FluoPath";
    MI_IMPORT_TYPES(Scene, Sampler, Emitter, BSDF, Shape)
    using EmitterSample = fluo_detail::EmitterSample<Float, Spectrum>;

    /// Largest supported basis size K.
    static constexpr size_t KMax = 7;
    using Row3 = std::array<double, 3 * KMax>;      // 3×K, row major
    using Square = std::array<double, KMax * KMax>; // K×K, row major
    using Coeffs = std::array<double, KMax>;

    /// The transport basis `basis` ("rgb", "xyzu", "x7") with reduction `method`
    /// ("ours", "naive"); errors name `plugin`.
    ReducedTransport(const char *plugin, const std::string &basis, const std::string &method)
        : m_plugin(plugin),
          m_transport(fluo_detail::rust_call(plugin, [&] { return fluo::transport_new(basis, method); })) {
        m_k = fluo::transport_size(*m_transport);
        if (m_k != 3 && m_k != 4 && m_k != KMax)
            Throw("%s: basis \"%s\" has %zu bands; the transport is compiled for 3, 4 and %zu",
                  plugin, basis, m_k, KMax);
        fluo::transport_output(*m_transport, rust::Slice<double>(m_output.data(), 3 * m_k));
        fluo::transport_from_rgb(*m_transport, rust::Slice<double>(m_from_rgb.data(), 3 * m_k));
        fluo::transport_white(*m_transport, rust::Slice<double>(m_white.data(), m_k));
    }

    /// The basis's name and its number of bands K.
    std::string basis_name() const { return std::string(fluo::transport_name(*m_transport)); }
    size_t bands() const { return m_k; }

    /// scalar_rgb: reduce every fluorescent BSDF for the transport basis (their
    /// wrappers go to `wrappers`), and find the emitters whose radiance has a known
    /// spectrum.
    void prepare(Scene *scene, fluo_detail::FluoWrappers<Float, Spectrum> &wrappers,
                 bool fluorescent_media = false) {
        m_entries.clear();
        m_varying.clear();
        m_reduced.clear();
        m_sources.clear();
        fluo_detail::Collector c;
        for (const auto &shape : scene->shapes())
            c.visit(const_cast<Shape *>(shape.get()));
        wrappers.scan(c, m_plugin);
        for (Object *o : c.objects) {
            auto *bsdf = dynamic_cast<BSDF *>(o);
            auto *bisp = dynamic_cast<BispectralBSDF<Float, Spectrum> *>(o);
            if (!bsdf || !bisp || !bisp->fluorescence())
                continue;
            if (bisp->fluorescence_varies()) {
                // A varying material with a finite set of models (fluo_jung's textured
                // parameters: one dye shape per (λe, s) pair) has each reduced once here and
                // scaled per vertex. Without such a set (fluo_jung's colour texture) it stays
                // a plain BSDF: its RGB value is the colour the upsampling cube reproduces.
                size_t n = bisp->fluorescence_models();
                if (n == 0)
                    continue;
                Entry e{ bsdf, bisp, nullptr };
                e.varies = true;
                e.first = m_varying.size();
                e.count = n;
                for (size_t i = 0; i < n; ++i) {
                    const fluo::Fluorescence *shape = bisp->fluorescence_model(i);
                    m_reduced.push_back(fluo_detail::rust_call(
                        m_plugin, [&] { return fluo::reduced_new(*shape, *m_transport); }));
                    VaryingModel sh{ &*m_reduced.back() };
                    sh.full = fluo::reduced_includes_elastic(*sh.reduced);
                    sh.lambertian = fluo::reduced_lambertian(*sh.reduced, rust::Slice<double>(sh.m.data(), m_k * m_k));
                    m_varying.push_back(sh);
                }
                m_entries.add(e);
                continue;
            }
            const fluo::Fluorescence *model = bisp->fluorescence();
            m_reduced.push_back(fluo_detail::rust_call(
                m_plugin, [&] { return fluo::reduced_new(*model, *m_transport); }));
            Entry e{ bsdf, bisp, &*m_reduced.back() };
            e.full = fluo::reduced_includes_elastic(*e.reduced);
            e.lambertian = fluo::reduced_lambertian(*e.reduced, rust::Slice<double>(e.m.data(), m_k * m_k));
            m_entries.add(e);
        }
        bool warned_uv = m_uv_warned == scene; // one warning per scene
        for (const auto &emitter : scene->emitters()) {
            fluo_detail::Collector ce;
            ce.visit(const_cast<Emitter *>(emitter.get()));
            for (Object *o : ce.objects)
                if (auto *src = dynamic_cast<SpectralSource *>(o)) {
                    EmitterSource es{ emitter.get(), {}, 0.0 };
                    fluo::illuminant_coefficients(src->illuminant(), *m_transport,
                                                  rust::Slice<double>(es.coeffs.data(), m_k));
                    es.luminance = src->rgb_luminance();
                    m_sources.push_back(es);
                    if (!warned_uv && (!m_entries.empty() || fluorescent_media) &&
                        fluo::illuminant_is_mostly_uv(src->illuminant())) {
                        warned_uv = true;
                        m_uv_warned = scene;
                        fluo_detail::warn_uv_emitter(m_plugin, "scalar_rgb", emitter.get());
                    }
                    break;
                }
        }
    }

    /// Whether the scene has fluorescent materials to transport (else fluo_path runs
    /// Mitsuba's path).
    bool active() const { return !m_entries.empty(); }
    /// Number of fluorescent BSDFs transported with reduced matrices.
    size_t size() const { return m_entries.size(); }

    /// A fluorescent BSDF of the scene and its reduced operator.
    struct Entry {
        const BSDF *bsdf;
        const BispectralBSDF<Float, Spectrum> *bispectral;
        const fluo::ReducedModel *reduced;
        /// Whether the reduced operator includes the elastic part (else eval_elastic adds it).
        bool full = false;
        /// A Lambertian model's M (f = M/π), read once at prepare time.
        bool lambertian = false;
        Square m{};
        /// Spatially varying (BispectralBSDF::fluorescence_local): its models are
        /// m_varying[first, first + count), `reduced` is unused.
        bool varies = false;
        size_t first = 0, count = 0;
    };

    /// One model of a varying material, reduced at prepare time.
    struct VaryingModel {
        const fluo::ReducedModel *reduced;
        bool full = false; ///< its matrix includes the elastic part (a measured material)
        bool lambertian = false;
        Square m{};
    };

    /// The material at a vertex: its entry, nullptr when it is not fluorescent.
    using Vertex = const Entry *;

    /// One camera path: RGB throughput t until its first fluorescent vertex, then the
    /// 3×K matrix R (see FluoPathLoop for the interface).
    class Path {
    public:
        explicit Path(const ReducedTransport &t) : m_t(t) {}

        Vertex begin_vertex(const BSDF *bsdf, SurfaceInteraction3f & /* si */, Sampler * /* sampler */) const {
            return m_t.find(bsdf);
        }

        void on_emission(const Emitter *emitter, const Spectrum &le, Float mis) {
            if (m_reduced)
                m_t.accumulate(m_result, m_R, m_t.emitter_coefficients(emitter, le), mis);
            else
                m_result = dr::fmadd(m_rgb, le * mis, m_result);
        }

        BSDFSample3f scatter(const Vertex &fl, const BSDF *bsdf, const SurfaceInteraction3f &si,
                             const EmitterSample &em, Float sample_1, const Point2f &sample_2) {
            BSDFContext bsdf_ctx;
            const Coeffs *light = m_light;
            m_light = nullptr;
            // --------------- Emitter sampling contribution ----------------
            if (em.active) {
                if (fl) {
                    Float mis_em = dr::select(em.ds.delta, 1.f,
                                              fluo_detail::mis_weight(em.ds.pdf, bsdf->pdf(bsdf_ctx, si, em.wo)));
                    // R·(M·c): a K×K matrix-vector product instead of the 3K×K product R·M.
                    Coeffs c = light ? *light : m_t.emitter_coefficients(em.ds.emitter, em.weight);
                    Coeffs mc = m_t.vertex_apply(*fl, si, em.wo, c, m_m);
                    m_t.accumulate(m_result, m_reduced ? m_R : m_t.rows_scaled(m_rgb), mc, mis_em);
                } else {
                    auto [val, bsdf_pdf] = bsdf->eval_pdf(bsdf_ctx, si, em.wo);
                    Float mis_em = dr::select(em.ds.delta, 1.f, fluo_detail::mis_weight(em.ds.pdf, bsdf_pdf));
                    if (m_reduced || light) {
                        Row3 rm = m_reduced ? m_R : m_t.rows_scaled(m_rgb);
                        m_t.scale_columns(rm, m_t.band_albedo(val));
                        Coeffs c = light ? *light : m_t.emitter_coefficients(em.ds.emitter, em.weight);
                        m_t.accumulate(m_result, rm, c, mis_em);
                    } else {
                        m_result = dr::fmadd(m_rgb, val * em.weight * mis_em, m_result);
                    }
                }
            }

            // ---------------------- BSDF sampling ----------------------
            auto [bs, weight] = bsdf->sample(bsdf_ctx, si, sample_1, sample_2);
            if (fl) {
                if (!m_reduced)
                    m_R = m_t.rows_scaled(m_rgb);
                m_reduced = true;
                if (bs.pdf > 0.f) {
                    m_t.vertex_multiply(*fl, si, bs.wo, m_R, 1.0 / bs.pdf, m_m);
                } else {
                    m_R.fill(0.0);
                }
            } else if (m_reduced) {
                m_t.scale_columns(m_R, m_t.band_albedo(weight));
            } else {
                m_rgb *= weight;
            }
            return bs;
        }

        double throughput_max() const {
            double throughput_max = 0.0;
            if (m_reduced) {
                for (size_t i = 0; i < 3 * m_t.m_k; ++i)
                    throughput_max = std::max(throughput_max, std::abs(m_R[i]));
            } else {
                throughput_max = (double) dr::max(m_rgb);
            }
            return throughput_max;
        }

        void roulette(Float rr_prob) {
            for (size_t i = 0; i < 3 * m_t.m_k; ++i)
                m_R[i] /= rr_prob;
            m_rgb /= rr_prob;
        }

        // ---------------- fluo_volpath's fluorescent media (scalar_rgb) ----------------

        /// The next scatter()'s emitter sample reached the vertex through a fluorescent
        /// medium: its light is given as basis coefficients `c` (the shadow ray's transfer
        /// applied to the emitter's coefficients), not by its RGB weight. Valid for that
        /// one call; nullptr: none.
        void set_light(const Coeffs *c) { m_light = c; }
        /// Switch to the 3×K form (a fluorescent medium acts on bands, not RGB).
        void to_reduced() {
            if (!m_reduced)
                m_R = m_t.rows_scaled(m_rgb);
            m_reduced = true;
        }
        /// A wavelength-preserving weight (native media, null interfaces, phase weights).
        void scale(const Spectrum &w) {
            if (m_reduced)
                m_t.scale_columns(m_R, m_t.band_albedo(w));
            else
                m_rgb *= w;
        }
        /// R ← R·M·s (to the 3×K form first).
        void multiply(const Square &m, double s) {
            to_reduced();
            m_t.multiply(m_R, m, s);
        }
        /// R ← (R·diag(g) − d·R·A)·s (3×K form): a fluorescent medium's null collision
        /// (A: its reduced absorption), without forming the K×K operator.
        void multiply_null(const Square &a, double d, const Coeffs &g, double s) {
            to_reduced();
            m_t.multiply_diag_plus(m_R, &g, a, -d, s);
        }

        /// result += R·(M·c)·s (RGB form: diag(t)·O·(M·c)·s) for light c.
        void add(const Square &m, const Coeffs &c, double s) {
            m_t.accumulate(m_result, m_reduced ? m_R : m_t.rows_scaled(m_rgb), m_t.apply(m, c), s);
        }
        /// result += R·diag(w)·c·s for a wavelength-preserving weight w and light c (basis
        /// coefficients); without c, light of RGB radiance le from emitter e (in the RGB
        /// form: t·w·le·s, as Mitsuba).
        void add_light(const Spectrum &w, const Emitter *e, const Spectrum &le, const Coeffs *c, double s) {
            if (!m_reduced && !c) {
                m_result = dr::fmadd(m_rgb, w * le * (Float) s, m_result);
                return;
            }
            Row3 rm = m_reduced ? m_R : m_t.rows_scaled(m_rgb);
            m_t.scale_columns(rm, m_t.band_albedo(w));
            m_t.accumulate(m_result, rm, c ? *c : m_t.emitter_coefficients(e, le), s);
        }
        /// Per band k, max over the rows of |R_rk| (3×K form).
        Coeffs column_max() const {
            Coeffs out{};
            for (size_t row = 0; row < 3; ++row)
                for (size_t k = 0; k < m_t.m_k; ++k)
                    out[k] = std::max(out[k], std::abs(m_R[row * m_t.m_k + k]));
            return out;
        }

        /// Out-of-gamut colours (a saturated 520 nm emission has negative linear sRGB
        /// red) are clipped here, per sample, as an sRGB film must store them; along
        /// the path the coefficients stay signed.
        Spectrum radiance() const { return Spectrum(dr::maximum(m_result, 0.f)); }

    private:
        const ReducedTransport &m_t;
        Row3 m_R{};
        Color3f m_rgb = 1.f;    // RGB throughput while no fluorescent vertex was met
        bool m_reduced = false; // whether m_R (not m_rgb) carries the throughput
        Color3f m_result = 0.f;
        Square m_m{};           // scratch: the current vertex matrix
        const Coeffs *m_light = nullptr; // set_light()
    };

    /// The transport basis (to reduce other operators for it).
    const fluo::TransportBasis &basis() const { return *m_transport; }

    /// Basis coefficients of an emitter's radiance: its spectrum's own coefficients
    /// (rescaled to the radiance's luminance) for a fluo_illuminant, else F times its RGB.
    Coeffs emitter_coefficients(const Emitter *e, const Spectrum &rgb) const {
        Coeffs c{};
        if constexpr (is_rgb_v<Spectrum>) {
            for (const EmitterSource &src : m_sources)
                if (src.emitter == e) {
                    double s = src.luminance > 0.0 ? luminance_of(rgb) / src.luminance : 0.0;
                    for (size_t k = 0; k < m_k; ++k)
                        c[k] = src.coeffs[k] * s;
                    return c;
                }
            for (size_t k = 0; k < m_k; ++k)
                c[k] = m_from_rgb[k * 3] * rgb[0] + m_from_rgb[k * 3 + 1] * rgb[1] +
                       m_from_rgb[k * 3 + 2] * rgb[2];
        }
        return c;
    }

    /// Per-band albedo a_k = (from_rgb · v)_k / (from_rgb · 1)_k of an RGB value: how a
    /// native (wavelength-preserving) BSDF, medium or phase weight acts on the K
    /// coefficients.
    Coeffs band_albedo(const Spectrum &v) const {
        Coeffs d{};
        if constexpr (is_rgb_v<Spectrum>) {
            double mean = (v[0] + v[1] + v[2]) / 3.0;
            for (size_t k = 0; k < m_k; ++k) {
                double num = m_from_rgb[k * 3] * v[0] + m_from_rgb[k * 3 + 1] * v[1] +
                             m_from_rgb[k * 3 + 2] * v[2];
                d[k] = std::abs(m_white[k]) > 1e-12 ? num / m_white[k] : mean;
            }
        }
        return d;
    }

private:
    struct EmitterSource {
        const Emitter *emitter;
        Coeffs coeffs;    // basis coefficients of its spectrum (as the texture is defined)
        double luminance; // luminance of the texture's RGB, to rescale by the emitter's
    };

    const Entry *find(const BSDF *bsdf) const { return m_entries.find(bsdf); }

    static fluo::Vec3 vec(const Vector3f &v) { return fluo::Vec3{ v.x(), v.y(), v.z() }; }

    static double luminance_of(const Spectrum &v) {
        if constexpr (is_rgb_v<Spectrum>)
            return 0.212671 * v[0] + 0.715160 * v[1] + 0.072169 * v[2];
        else
            return 0.0;
    }

    /// Calls f(std::integral_constant<size_t, K>{}) with the transport's K, so that the
    /// matrix loops below have compile-time bounds (unrolled, vectorised, no reloads of
    /// m_k through the aliasing the build flags allow). The constructor admits only
    /// these three sizes.
    template <typename F> void with_k(F &&f) const {
        switch (m_k) {
            case 3: f(std::integral_constant<size_t, 3>{}); break;
            case 4: f(std::integral_constant<size_t, 4>{}); break;
            default: f(std::integral_constant<size_t, KMax>{}); break;
        }
    }

    /// M · c.
    Coeffs apply(const Square &m, const Coeffs &c) const {
        Coeffs out{};
        with_k([&](auto kc) {
            constexpr size_t K = decltype(kc)::value;
            for (size_t i = 0; i < K; ++i) {
                double acc = 0.0;
                for (size_t k = 0; k < K; ++k)
                    acc += m[i * K + k] * c[k];
                out[i] = acc;
            }
        });
        return out;
    }
    /// R ← R · diag(d): native vertices cost 3K products, not a dense 3K×K product.
    void scale_columns(Row3 &r, const Coeffs &d) const {
        with_k([&](auto kc) {
            constexpr size_t K = decltype(kc)::value;
            for (size_t row = 0; row < 3; ++row)
                for (size_t j = 0; j < K; ++j)
                    r[row * K + j] *= d[j];
        });
    }

    /// Factor of a Lambertian entry's M for directions (wi, wo): cos θo/π on the upper
    /// hemisphere (f = M/π times cos θo), else 0.
    static double lambertian_factor(const SurfaceInteraction3f &si, const Vector3f &wo) {
        double ci = (double) Frame3f::cos_theta(si.wi), co = (double) Frame3f::cos_theta(wo);
        return ci > 0.0 && co > 0.0 ? co * 0.31830988618379067154 : 0.0; // 1/π, as Rust
    }
    /// Per-band elastic albedo at the vertex, zero when the reduced operator includes it.
    Coeffs elastic_diagonal(const Entry &e, const SurfaceInteraction3f &si, const Vector3f &wo) const {
        return e.full ? Coeffs{} : band_albedo(Spectrum(e.bispectral->eval_elastic(si, wo)));
    }

    /// The K×K vertex matrix of a direction-dependent fluorescent BSDF for direction wo
    /// (value · cos): the reduced reradiation, plus the elastic diagonal d.
    void fluorescent_matrix(const Entry &e, const SurfaceInteraction3f &si, const Vector3f &wo,
                            const Coeffs &d, Square &m) const {
        with_k([&](auto kc) {
            constexpr size_t K = decltype(kc)::value;
            fluo::reduced_reradiation(*e.reduced, vec(si.wi), vec(wo), rust::Slice<double>(m.data(), K * K));
            for (size_t k = 0; k < K; ++k)
                m[k * K + k] += d[k];
        });
    }

    /// The K×K vertex matrix of a spatially varying material at si for direction wo:
    /// its mixture's reduced models (BispectralBSDF::Local), each scaled by prob·weight;
    /// models whose matrix includes the elastic part (measured materials, weight 1)
    /// cover their share `prob` of it, eval_elastic the rest.
    void varying_matrix(const Entry &e, const SurfaceInteraction3f &si, const Vector3f &wo, Square &m) const {
        m.fill(0.0);
        typename BispectralBSDF<Float, Spectrum>::Mixture mix;
        size_t n = e.bispectral->fluorescence_local(si, mix);
        double covered = 0.0;
        for (size_t k = 0; k < n; ++k) {
            const auto &l = mix[k];
            if (!l.model || l.index >= e.count || !(l.weight * l.prob > 0.0))
                continue; // no re-emission from this entry
            const VaryingModel &v = m_varying[e.first + l.index];
            if (v.full)
                covered += l.prob;
            add_reradiation(v.reduced, v.lambertian, v.m, si, wo, l.weight * l.prob, m);
        }
        if (covered < 1.0) {
            Coeffs d = band_albedo(Spectrum(e.bispectral->eval_elastic(si, wo)));
            for (size_t k = 0; k < m_k; ++k)
                m[k * m_k + k] += d[k] * (1.0 - covered);
        }
    }

    /// m += scale · (a reduced model's reradiation matrix for wo, times cos θo).
    void add_reradiation(const fluo::ReducedModel *reduced, bool lambertian, const Square &lm,
                         const SurfaceInteraction3f &si, const Vector3f &wo, double scale, Square &m) const {
        if (lambertian) { // f = M/π, times cos θo: no bridge call per direction
            double factor = lambertian_factor(si, wo) * scale;
            for (size_t i = 0; i < m_k * m_k; ++i)
                m[i] += lm[i] * factor;
            return;
        }
        Square r{};
        fluo::reduced_reradiation(*reduced, vec(si.wi), vec(wo), rust::Slice<double>(r.data(), m_k * m_k));
        for (size_t i = 0; i < m_k * m_k; ++i)
            m[i] += r[i] * scale;
    }

    /// M(wo) · c for the vertex matrix M of a fluorescent BSDF (`scratch`: workspace).
    /// A Lambertian entry is applied as (cos θo/π)·(M·c) + d∘c, without forming M.
    Coeffs vertex_apply(const Entry &e, const SurfaceInteraction3f &si, const Vector3f &wo, const Coeffs &c,
                        Square &scratch) const {
        if (e.varies) {
            varying_matrix(e, si, wo, scratch);
            return apply(scratch, c);
        }
        Coeffs d = elastic_diagonal(e, si, wo);
        if (!e.lambertian) {
            fluorescent_matrix(e, si, wo, d, scratch);
            return apply(scratch, c);
        }
        Coeffs out = apply(e.m, c);
        double f = lambertian_factor(si, wo);
        for (size_t k = 0; k < m_k; ++k)
            out[k] = out[k] * f + d[k] * c[k];
        return out;
    }

    /// R ← R · M(wo) · s for the vertex matrix M of a fluorescent BSDF. A Lambertian
    /// entry is applied as (R·M)·(cos θo/π)·s + R·diag(d)·s, without forming M.
    void vertex_multiply(const Entry &e, const SurfaceInteraction3f &si, const Vector3f &wo, Row3 &r, double s,
                         Square &scratch) const {
        if (e.varies) {
            varying_matrix(e, si, wo, scratch);
            multiply(r, scratch, s);
            return;
        }
        Coeffs d = elastic_diagonal(e, si, wo);
        if (!e.lambertian) {
            fluorescent_matrix(e, si, wo, d, scratch);
            multiply(r, scratch, s);
            return;
        }
        double f = lambertian_factor(si, wo) * s;
        with_k([&](auto kc) {
            constexpr size_t K = decltype(kc)::value;
            std::array<double, 3 * K> out;
            for (size_t row = 0; row < 3; ++row)
                for (size_t j = 0; j < K; ++j) {
                    double acc = 0.0;
                    for (size_t k = 0; k < K; ++k)
                        acc += r[row * K + k] * e.m[k * K + j];
                    out[row * K + j] = acc * f + r[row * K + j] * d[j] * s;
                }
            std::copy(out.begin(), out.end(), r.begin());
        });
    }

    /// R ← R · M · s
    void multiply(Row3 &r, const Square &m, double s) const { multiply_diag_plus(r, nullptr, m, 1.0, s); }

    /// R ← (R·diag(g) + c·R·M)·s (without g: c·R·M·s).
    void multiply_diag_plus(Row3 &r, const Coeffs *g, const Square &m, double c, double s) const {
        Coeffs gs{}; // g·s, or 0
        if (g)
            for (size_t j = 0; j < KMax; ++j)
                gs[j] = (*g)[j] * s;
        double cs = c * s;
        with_k([&](auto kc) {
            constexpr size_t K = decltype(kc)::value;
            std::array<double, 3 * K> out;
            for (size_t row = 0; row < 3; ++row)
                for (size_t j = 0; j < K; ++j) {
                    double acc = 0.0;
                    for (size_t k = 0; k < K; ++k)
                        acc += r[row * K + k] * m[k * K + j];
                    out[row * K + j] = r[row * K + j] * gs[j] + cs * acc;
                }
            std::copy(out.begin(), out.end(), r.begin());
        });
    }

    /// result += R · c · s
    void accumulate(Color3f &result, const Row3 &r, const Coeffs &c, double s) const {
        with_k([&](auto kc) {
            constexpr size_t K = decltype(kc)::value;
            for (size_t row = 0; row < 3; ++row) {
                double acc = 0.0;
                for (size_t k = 0; k < K; ++k)
                    acc += r[row * K + k] * c[k];
                result[row] += (float) (acc * s);
            }
        });
    }

    /// R = diag(t) · m_output: the 3×K throughput of an RGB throughput t.
    Row3 rows_scaled(const Color3f &t) const {
        Row3 r = m_output;
        for (size_t row = 0; row < 3; ++row)
            for (size_t k = 0; k < m_k; ++k)
                r[row * m_k + k] *= (double) t[row];
        return r;
    }

    const char *m_plugin;
    rust::Box<fluo::TransportBasis> m_transport;
    size_t m_k = 3;
    Row3 m_output{}, m_from_rgb{};
    Coeffs m_white{};
    std::vector<rust::Box<fluo::ReducedModel>> m_reduced;
    std::vector<VaryingModel> m_varying; ///< the models of varying materials (Entry::first)
    fluo_detail::EntryTable<Entry> m_entries;
    std::vector<EmitterSource> m_sources;
    const Scene *m_uv_warned = nullptr; ///< the scene last warned of a UV emitter
};

NAMESPACE_END(mitsuba)
