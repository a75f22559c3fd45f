// What fluo_path and fluo_volpath share around their loops (each loop its own, in the shape
// of Mitsuba's path.cpp and volpath.cpp): the parameters lambda_min, basis and method, the
// render's preparation, the derivative passes and sample()'s replay passes.
#pragma once

#include <mitsuba/core/properties.h>
#include <mitsuba/render/integrator.h>

#include <type_traits>
#include <utility>

#include "fluo_reduced.h"

NAMESPACE_BEGIN(mitsuba)

/// A fluorescent integrator (registered as `plugin` and, as path replay, as `replay`):
/// the derived class prepares a render (prepare(): the fluorescent BSDFs of the scene, the
/// lights' range, the reduced transport) and traces one sample (trace_sample(), its loop).
/// Derivatives differentiate the recorded loop, or replay each path when registered as
/// `Replay` (fluo_detail::PathReplay: every AD variant but the polarized ones).
template <typename Float, typename Spectrum> class FluoIntegrator : public MonteCarloIntegrator<Float, Spectrum> {
public:
    MI_IMPORT_BASE(MonteCarloIntegrator, m_max_depth)
    MI_IMPORT_TYPES(Scene, Sensor, Sampler, Medium)
    using Bispectral = fluo_detail::BispectralBSDF<Float, Spectrum>;
    using Reduced = fluo_detail::ReducedTransport<Float, Spectrum>;
    using Wrappers = fluo_detail::FluoWrappers<Float, Spectrum>;
    using WMask = dr::mask_t<UnpolarizedSpectrum>;
    template <size_t K> using Coeffs = typename Reduced::template Coeffs<K>;
    template <size_t K> using Rows = typename Reduced::template Rows<K>;

    /// What a path carries in the reduced transport (K > 0, RGB with fluorescence): Mitsuba's
    /// RGB throughput t until the first fluorescent event, then the 3×K matrix throughput R.
    template <size_t K> struct MatrixThroughput {
        Color3f t;
        Rows<K> R;
        Mask reduced; ///< where R is the throughput
        DRJIT_STRUCT(MatrixThroughput, t, R, reduced)
    };
    /// `Throughput` (the derived loop's, K = 0) or MatrixThroughput<K>.
    template <size_t K, typename Throughput>
    using Carried = std::conditional_t<K == 0, Throughput, MatrixThroughput<K>>;

    FluoIntegrator(const Properties &props, const char *plugin, const char *replay, const char *basis)
        : Base(props), m_lambda_min(fluo_detail::lambda_min_of(plugin, props)),
          m_reduced(plugin, fluo_detail::get_string(props, "basis", basis),
                    fluo_detail::get_string(props, "method", "ours")),
          m_plugin(plugin), m_replay_plugin(replay), m_replay(props.plugin_name() == replay) {
        if (m_replay && is_polarized_v<Spectrum>)
            Throw("%s: path replay is not available in the polarized variants (its adjoint divides the "
                  "throughput per wavelength, which a Mueller matrix does not allow); render them with %s, "
                  "whose gradients differentiate the recorded loop",
                  replay, plugin);
    }

    using Base::render;
    TensorXf render(Scene *scene, Sensor *sensor, UInt32 seed, uint32_t spp, bool develop,
                    bool evaluate) override {
        prepare_render(scene);
        if (Base *d = delegate())
            return d->render(scene, sensor, seed, spp, develop, evaluate);
        return Base::render(scene, sensor, seed, spp, develop, evaluate);
    }

    // Derivatives recorded through the loop weigh BSDF samples as the replay does
    // (fluo_detail::detach_moving_sample).
    using Base::render_forward;
    TensorXf render_forward(Scene *scene, void *params, Sensor *sensor, UInt32 seed, uint32_t spp) override {
        fluo_detail::Raised on{ m_differentiating };
        return Base::render_forward(scene, params, sensor, seed, spp);
    }
    using Base::render_backward;
    void render_backward(Scene *scene, void *params, const TensorXf &grad_in, Sensor *sensor, UInt32 seed,
                         uint32_t spp) override {
        fluo_detail::Raised on{ m_differentiating };
        if constexpr (dr::is_diff_v<Float> && !is_polarized_v<Spectrum>) {
            if (m_replay) {
                prepare_render(scene);
                if (m_max_depth == 0)
                    return; // nothing is rendered, nothing depends on the parameters
                // (the primal's radiance is clipped per sample where the reduced transport runs)
                return m_replayer.backward(
                    m_replay_plugin, [&](bool develop) { return Base::render(scene, sensor, seed, spp, develop, false); },
                    sensor, grad_in, spp, clipped());
            }
        }
        Base::render_backward(scene, params, grad_in, sensor, seed, spp);
    }

    std::pair<Spectrum, Bool> sample(const Scene *scene, Sampler *sampler, const RayDifferential3f &ray,
                                     const Medium *medium, Float *aovs, Bool active) const override {
        if (auto seed = m_replayer.seed(m_replay_plugin, dr::width(ray))) // the replay's first pass
            return *seed;
        m_prepared.ensure(scene, [&] { const_cast<FluoIntegrator *>(this)->prepare(const_cast<Scene *>(scene)); });
        if (Base *d = delegate())
            return d->sample(scene, sampler, ray, medium, aovs, active);
        if (unlikely(m_max_depth == 0))
            return { 0.f, false };
        // (the replay's primal pass unclipped: it differentiates where a colour was not clipped)
        if (m_replayer.replay(
                [&](bool adjoint) { return trace_sample(scene, sampler, ray, medium, aovs, active, adjoint, false); }))
            return { 0.f, false };
        return trace_sample(scene, sampler, ray, medium, aovs, active, false, true);
    }

protected:
    /// Once per render (and again after an update of fluo's plugins): what the loop reads.
    virtual void prepare(Scene *scene) = 0;
    /// One sample's radiance (the loop); `adjoint`: the replay's third pass; `clip`: the
    /// reduced transport clips out-of-gamut colours (not in the replay's primal pass).
    virtual std::pair<Spectrum, Bool> trace_sample(const Scene *scene, Sampler *sampler, const RayDifferential3f &ray,
                                                   const Medium *medium, Float *aovs, Bool active, bool adjoint,
                                                   bool clip) const = 0;
    /// Whether the loop clips its radiance per sample (the reduced transport runs).
    virtual bool clipped() const = 0;
    /// An integrator that renders the prepared scene instead (nothing fluoresces), if any.
    virtual Base *delegate() const { return nullptr; }

    /// dr::while_loop over the loop state `ls`: `step(ls)` while ls.active.
    template <typename State, typename Step> static void loop(State &ls, Step &&step) {
        dr::tie(ls) = dr::while_loop(
            dr::make_tuple(ls), [](const State &s) { return s.active; }, [&step](State &s) { step(s); });
    }

    void prepare_render(Scene *scene) {
        prepare(scene);
        m_prepared.mark(scene);
    }

    /// `f(std::integral_constant<size_t, K>{})` with K the reduced transport's band count
    /// where `reduced` (RGB variants), else K = 0 (Mitsuba's throughput).
    template <typename F> auto with_bands(bool reduced, F &&f) const {
        if constexpr (is_rgb_v<Spectrum>) {
            if (reduced) {
                if (m_reduced.bands() == 3)
                    return f(std::integral_constant<size_t, 3>{});
                if (m_reduced.bands() == 4)
                    return f(std::integral_constant<size_t, 4>{});
                if (m_reduced.bands() == 7)
                    return f(std::integral_constant<size_t, 7>{});
                return f(std::integral_constant<size_t, Reduced::KMax>{}); // auto with two light bands
            }
        }
        return f(std::integral_constant<size_t, 0>{});
    }

    /// The render's fluorescent BSDFs (their wrappers scanned; none in a scene without
    /// emitters) and m_range_lo/hi: the lights' range from lambda_min, widened to what those
    /// BSDFs and `reemitted` (fluorescent media) re-emit, since re-emitted light can excite
    /// further shifts. Sets m_directional: one of them keeps a direction-dependent lobe
    /// (fluo_detail::keep_excited).
    std::vector<Bispectral *> scan(Scene *scene, double reemitted) {
        fluo::Range lights = fluo_detail::emitters_range(scene);
        m_range_lo = std::max(lights.lo, m_lambda_min);
        m_range_hi = std::max(lights.hi, reemitted);
        fluo_detail::Collector objects = fluo_detail::shape_objects(scene);
        m_wrappers.scan(objects, m_plugin);
        std::vector<Bispectral *> bsdfs = fluo_detail::fluorescent_bsdfs<Bispectral>(objects);
        for (Bispectral *b : bsdfs)
            m_range_hi = std::max(m_range_hi, b->jit_emission_range().hi);
        m_directional = fluo_detail::keep_excited<Spectrum>(bsdfs, m_range_lo, m_range_hi);
        if (scene->emitters().empty())
            bsdfs.clear();
        m_directional &= !bsdfs.empty();
        return bsdfs;
    }

    double m_lambda_min = 300.0;
    Reduced m_reduced; ///< RGB variants: the reduced transport
    fluo_detail::FluorescentSet<Float, Spectrum> m_bsdfs; ///< fluorescent BSDFs this render
    double m_range_lo = 0.0, m_range_hi = 0.0;           ///< the lights' range, widened by re-emission
    Wrappers m_wrappers;                                  ///< around fluorescent BSDFs, this render
    bool m_directional = false; ///< some fluorescent BSDF has a direction-dependent lobe
    bool m_varying = false;     ///< ... that varies over the surface (RGB: a model picked per vertex)
    const char *m_plugin, *m_replay_plugin;
    bool m_replay = false;          ///< registered as the path replay
    bool m_differentiating = false; ///< in render_forward/backward (recorded AD of the loop)
    mutable fluo_detail::PreparedScene m_prepared;       ///< the scene prepared last (nested use)
    fluo_detail::PathReplay<Float, Spectrum> m_replayer; ///< the replay's passes
};

NAMESPACE_END(mitsuba)
