// fluo_path's wavelength-shifting transport: Mitsuba's throughput (per hero
// wavelength in scalar_spectral, RGB in scalar_rgb) and, at a fluorescent vertex,
// the per-wavelength choice between the elastic event and a shift λo -> λi (the
// estimator and its unbiasedness are in fluo_path's docs). Without fluorescent
// vertices it is Mitsuba's `path`: the same arithmetic and random numbers. It plugs
// into FluoPathLoop (fluo_path_loop.h) as its `Path`.
#pragma once

#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/emitter.h>
#include <mitsuba/render/scene.h>
#include <mitsuba/render/texture.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <vector>

#include "fluo_bispectral.h"
#include "fluo_path_loop.h"
#include "fluo_path_scene.h"

NAMESPACE_BEGIN(mitsuba)

template <typename Float, typename Spectrum> class SpectralTransport {
public:
    MI_IMPORT_TYPES(Scene, Sampler, Emitter, BSDF, Texture, Shape)
    using EmitterSample = fluo_detail::EmitterSample<Float, Spectrum>;

    /// A fluorescent BSDF of the scene with the excitation range it can use.
    struct Entry {
        const BSDF *bsdf;
        const BispectralBSDF<Float, Spectrum> *bispectral;
        const fluo::Fluorescence *model;
        fluo::Range range;
        /// Spatially varying: the model and its range are looked up per vertex.
        bool varies = false;
        /// Its shift albedo over `range`, tabulated at prepare time (not when varying).
        const fluo::ShiftTable *shift = nullptr;
    };

    /// scalar_spectral: scan the scene once per render (the emitters' spectral range
    /// and the fluorescent BSDFs, whose wrappers go to `wrappers`). `lambda_min` (nm)
    /// bounds the excitation range from below; `emission_hi` (nm) is the longest
    /// wavelength other re-emitters found by the caller emit (fluo_volpath's media).
    void prepare(Scene *scene, fluo_detail::FluoWrappers<Float, Spectrum> &wrappers, double lambda_min,
                 const char *plugin, double emission_hi = -1e30) {
        m_entries.clear();
        m_shift_tables.clear();
        // Where can light exist? The union of the emitters' radiance spectra.
        fluo::Range lights = fluo_detail::emitters_range(scene);
        double lo = lights.lo, hi = lights.hi;
        if (scene->emitters().empty())
            return;
        lo = std::max(lo, lambda_min);

        // Fluorescent BSDFs anywhere in the scene graph.
        fluo_detail::Collector c;
        for (const auto &shape : scene->shapes())
            c.visit(const_cast<Shape *>(shape.get()));
        wrappers.scan(c, plugin);
        std::vector<Entry> candidates;
        hi = std::max(hi, emission_hi);
        for (Object *o : c.objects) {
            auto *bsdf = dynamic_cast<BSDF *>(o);
            auto *bisp = dynamic_cast<BispectralBSDF<Float, Spectrum> *>(o);
            if (!bsdf || !bisp || !bisp->fluorescence())
                continue;
            const fluo::Fluorescence *model = bisp->fluorescence();
            fluo::Range em = fluo::fluo_emission_range(*model);
            hi = std::max(hi, em.hi); // re-emitted light can excite further shifts
            candidates.push_back(Entry{ bsdf, bisp, model, fluo::Range{ 0, 0 }, bisp->fluorescence_varies() });
        }
        m_range = fluo::Range{ lo, hi };
        for (Entry &e : candidates) {
            fluo::Range ex = fluo::fluo_excitation_range(*e.model);
            // Varying materials: only the light's range; each vertex intersects it
            // with its own model's excitation range.
            e.range = e.varies ? fluo::Range{ lo, hi }
                               : fluo::Range{ std::max(ex.lo, lo), std::min(ex.hi, hi) };
            if (!(e.range.lo < e.range.hi))
                continue;
            if (!e.varies) {
                m_shift_tables.push_back(fluo::shift_table_new(*e.model, e.range, e.range.lo));
                e.shift = &*m_shift_tables.back();
            }
            m_entries.add(e);
        }
    }

    /// Number of fluorescent BSDFs transported with wavelength shifts.
    size_t size() const { return m_entries.size(); }
    /// The excitation range R (nm) found by prepare().
    fluo::Range range() const { return m_range; }

    /// Per-wavelength choice at a fluorescent vertex.
    struct Transition {
        std::array<bool, 4> shifted{};
        std::array<double, 4> lambda_o{}, lambda_i{};
        std::array<float, 4> scale{};
        /// The model at this vertex (per texel for spatially varying materials)...
        const fluo::Fluorescence *model = nullptr;
        /// ... and its scale there (BispectralBSDF::Local; 1 for uniform materials).
        double weight = 1.0;
    };

    /// The material at a vertex: its entry (nullptr: not fluorescent) and transitions.
    struct Vertex {
        const Entry *entry = nullptr;
        Transition tr;
    };

    /// One camera path: throughput and radiance (see FluoPathLoop for the interface).
    class Path {
    public:
        explicit Path(const SpectralTransport &t) : m_t(t) {}

        Vertex begin_vertex(const BSDF *bsdf, SurfaceInteraction3f &si, Sampler *sampler) const {
            // Choose, per hero wavelength, the elastic event or a shift λo -> λi.
            Vertex v;
            v.entry = m_t.find(bsdf);
            if (v.entry)
                v.tr = m_t.choose_transitions(*v.entry, si, sampler);
            return v;
        }

        void on_emission(const Emitter * /* emitter */, const Spectrum &le, Float mis) {
            m_result = dr::fmadd(m_throughput, le * mis, m_result);
        }

        BSDFSample3f scatter(const Vertex &v, const BSDF *bsdf, const SurfaceInteraction3f &si,
                             const EmitterSample &em, Float sample_1, const Point2f &sample_2) {
            BSDFContext bsdf_ctx;
            // ------ Evaluate BSDF * cos(theta) and sample direction -------
            auto [bsdf_val, bsdf_pdf, bsdf_sample, bsdf_weight] =
                bsdf->eval_pdf_sample(bsdf_ctx, si, em.wo, sample_1, sample_2);

            if (v.entry) {
                m_t.apply_transitions(v.tr, si, em.wo, bsdf_val);
                if (bsdf_sample.pdf > 0.f) {
                    bsdf_weight *= bsdf_sample.pdf; // back to BSDF value (elastic slots)
                    m_t.apply_transitions(v.tr, si, bsdf_sample.wo, bsdf_weight);
                    bsdf_weight /= bsdf_sample.pdf;
                }
            }

            // --------------- Emitter sampling contribution ----------------
            if (em.active) {
                bsdf_val = si.to_world_mueller(bsdf_val, -em.wo, si.wi);
                Float mis_em = dr::select(em.ds.delta, 1.f, fluo_detail::mis_weight(em.ds.pdf, bsdf_pdf));
                m_result = dr::fmadd(m_throughput, bsdf_val * em.weight * mis_em, m_result);
            }

            // ---------------------- BSDF sampling ----------------------
            bsdf_weight = si.to_world_mueller(bsdf_weight, -bsdf_sample.wo, si.wi);
            m_throughput *= bsdf_weight;
            return bsdf_sample;
        }

        /// fluo_volpath's medium events: the throughput, and radiance arriving at it.
        Spectrum &throughput() { return m_throughput; }
        void add_radiance(const Spectrum &value) { m_result = dr::fmadd(m_throughput, value, m_result); }

        double throughput_max() const { return (double) dr::max(unpolarized_spectrum(m_throughput)); }
        void roulette(Float rr_prob) { m_throughput *= dr::rcp(rr_prob); }
        Spectrum radiance() const { return m_result; }

    private:
        const SpectralTransport &m_t;
        Spectrum m_throughput = 1.f;
        Spectrum m_result = 0.f;
    };

private:
    static constexpr size_t N = dr::size_v<Spectrum> == 4 ? 4 : 1;

    const Entry *find(const BSDF *bsdf) const { return m_entries.find(bsdf); }

    static fluo::Vec3 vec(const Vector3f &v) { return fluo::Vec3{ v.x(), v.y(), v.z() }; }

    /// Pick elastic or shifted per wavelength (see the unbiasedness note in fluo_path's
    /// docs) and move si.wavelengths to the excitation wavelengths.
    Transition choose_transitions(const Entry &e, SurfaceInteraction3f &si, Sampler *sampler) const {
        Transition tr;
        if constexpr (is_spectral_v<Spectrum>) {
            tr.model = e.model;
            fluo::Range range = e.range;
            if (e.varies) {
                // One entry of the material's mixture at si, picked with its probability.
                typename BispectralBSDF<Float, Spectrum>::Mixture mix;
                size_t n = e.bispectral->fluorescence_local(si, mix), k = 0;
                if (n > 1) {
                    double u = sampler->next_1d(), acc = 0.0;
                    for (k = 0; k + 1 < n; ++k) {
                        acc += mix[k].prob;
                        if (u < acc)
                            break;
                    }
                }
                tr.model = n > 0 && mix[k].weight > 0.0 ? mix[k].model : nullptr;
                tr.weight = n > 0 ? mix[k].weight : 0.0;
                if (tr.model) {
                    fluo::Range ex = fluo::fluo_excitation_range(*tr.model);
                    range = fluo::Range{ std::max(ex.lo, e.range.lo), std::min(ex.hi, e.range.hi) };
                }
                if (!tr.model || !(range.lo < range.hi)) {
                    tr.model = nullptr;
                    tr.scale.fill(1.f); // no fluorescence here: every wavelength elastic
                    return tr;
                }
            }
            auto albedo = e.bispectral->elastic_albedo(si);
            fluo::Vec3 wi = vec(si.wi);
            for (size_t j = 0; j < N; ++j) {
                double lo = si.wavelengths[j];
                tr.lambda_o[j] = tr.lambda_i[j] = lo;
                double we = std::max(0.0, (double) albedo[j]);
                double wf = std::max(0.0, e.shift ? fluo::shift_table_albedo(*e.shift, *tr.model, wi, lo)
                                                  : tr.weight * fluo::fluo_shift_albedo(*tr.model, wi, lo, range));
                Point2f u = sampler->next_2d();
                double total = we + wf;
                if (!(total > 0.0) || !std::isfinite(total)) {
                    tr.scale[j] = 0.f;
                    continue;
                }
                double pe = we / total;
                if (u.x() < pe) {
                    tr.scale[j] = (float) (1.0 / pe);
                    continue;
                }
                fluo::Sample s = fluo::fluo_sample_excitation(*tr.model, wi, lo, u.y(), range);
                if (!(s.pdf > 0.0)) {
                    tr.scale[j] = 0.f;
                    continue;
                }
                tr.shifted[j] = true;
                tr.lambda_i[j] = s.value;
                tr.scale[j] = (float) (1.0 / ((1.0 - pe) * s.pdf));
                si.wavelengths[j] = (float) s.value;
            }
        }
        return tr;
    }

    /// Turn the elastic BSDF value (times cos) into the chosen transitions' values.
    void apply_transitions(const Transition &tr, const SurfaceInteraction3f &si, const Vector3f &wo,
                           Spectrum &value) const {
        if constexpr (is_spectral_v<Spectrum>) {
            if (!tr.model)
                return; // all elastic at this vertex
            fluo::Vec3 wi = vec(si.wi), o = vec(wo);
            for (size_t j = 0; j < N; ++j) {
                if (tr.shifted[j])
                    value[j] = (float) (tr.weight * fluo::fluo_reradiation(*tr.model, wi, o, tr.lambda_i[j],
                                                                           tr.lambda_o[j]));
                value[j] *= tr.scale[j];
            }
        }
    }

    fluo_detail::EntryTable<Entry> m_entries;
    std::vector<rust::Box<fluo::ShiftTable>> m_shift_tables;
    fluo::Range m_range{ 0, 0 };
};

NAMESPACE_END(mitsuba)
