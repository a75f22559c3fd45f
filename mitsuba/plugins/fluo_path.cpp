#include <mitsuba/core/properties.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/emitter.h>
#include <mitsuba/render/integrator.h>
#include <mitsuba/render/records.h>
#include <mitsuba/render/texture.h>

#include <algorithm>
#include <unordered_set>
#include <vector>

#include "fluo_bispectral.h"
#include "fluo_common.h"

NAMESPACE_BEGIN(mitsuba)

/**!

.. _integrator-fluo_path:

Wavelength-shifting path tracer (:monosp:`fluo_path`)
-----------------------------------------------------

.. pluginparameters::

 * - max_depth
   - |int|
   - Longest path depth; -1 means infinite, 1 only direct emission. (Default: -1)
 * - rr_depth
   - |int|
   - Depth at which Russian roulette starts. (Default: 5)
 * - hide_emitters
   - |bool|
   - Hide directly visible emitters. (Default: false)
 * - basis
   - |string|
   - ``scalar_rgb`` only: transport basis for fluorescence, ``rgb`` (3 channels),
     ``xyzu`` (CIE 1931 XYZ plus a UV band) or ``x7`` (7 bands: X split in three, Y in two,
     Z, U). (Default: ``x7``: over the ``fluo bench`` scenes its mean ΔE00 against the
     spectral reference is the lowest on average and within noise of the best on each
     scene; README's generated bench table has the numbers. Its 7×7 matrices cost 392
     bytes per material and no measurable time over ``xyzu``.) Which basis when
     (``fluo-rs saturated-report`` and the second table of ``fluo bench`` measure it
     per basis): ``x7`` for saturated, narrow-band
     emitters (a pure green dye keeps its luminance within 20 % under daylight and
     incandescent light, where ``rgb`` and ``xyzu`` lose a third or more) and for
     anything excited in the UV; ``xyzu`` when materials are broad and 4×4 matrices
     matter; ``rgb`` only for scenes without UV excitation (it has no UV band: an
     optical brightener's reradiation under daylight all but vanishes) or to compare
     with a plain RGB renderer. Under narrow UV lamps every basis is coarse: one UV band
     averages a dye's absorption over 300-400 nm (a brightener under a 365 nm lamp glows
     ~5x too dark in ``xyzu``/``x7``, and not at all in ``rgb``); fluo_path warns once per
     scene when an emitter is mostly ultraviolet. Render such scenes in
     ``scalar_spectral``.
 * - method
   - |string|
   - ``scalar_rgb`` only: reduction of the reradiation, ``ours`` (dual basis, Fichet et
     al. 2024 eq. 15) or ``naive`` (eq. 7, for comparison only). (Default: ``ours``)
 * - lambda_min
   - |float|
   - Shortest excitation wavelength the integrator will ever shift to, nm, in
     [200, 360]. Spectrally defined emitters reach below the camera's 360 nm down
     to here. (Default: 300)

Unidirectional path tracing with next-event estimation and MIS, Russian roulette and
``max_depth``/``rr_depth``/``hide_emitters`` exactly as Mitsuba's ``path``, extended
with fluorescence (wavelength shifting) for fluo's bispectral BSDFs (``fluo_jung``
and the other ``fluo_*`` materials) in ``scalar_spectral``.

**Simulate only what the scene calls for.** At the start of each render the scene is
scanned once: the fluorescent BSDFs (those implementing fluo's bispectral interface
and re-emitting at all) and the spectral range of every emitter's radiance texture.
Light exists only where emitters emit or fluorescence re-emits, so excitation is
sampled only inside R = [max(emitters' min, lambda_min), max(emitters' max,
emission max)]. A material whose absorption band misses R is treated as a plain
BSDF. With nothing left, this integrator runs exactly Mitsuba's ``path`` (the same
code, the same random numbers: identical images), in both variants.

**Fluorescence in RGB (reduced transport).** In ``scalar_rgb`` a scene with fluorescent
materials is rendered with matrix throughput (Fichet et al. 2024, sec. 5.1, adjoint
transport). A camera path carries Mitsuba's RGB throughput t, exactly as ``path`` does,
until it meets its first fluorescent vertex: light that never meets a fluorescent
material (native walls lit by native or ``fluo_illuminant`` lights) renders exactly as
``path`` renders it, under every basis (before this, native vertices were always basis
diagonals, and the walls of a Cornell box with one fluorescent object came out 13.7 %
(``xyzu``) and 4.8 % (``x7``) off). At the first fluorescent vertex t becomes a 3×K
matrix R = diag(t)·O (O from K basis coefficients to linear sRGB), which from then on
is multiplied at each vertex by a K×K matrix: the material's
reduced operator (core/src/reduce/): the whole operator (elastic diagonal and reradiation,
as in the paper) when its elastic reflectance is known spectrally (sigmoid
``coefficients``, measured data), otherwise the reduced reradiation plus the elastic
RGB albedo (e.g. a texture) as a diagonal. Native BSDFs met after a fluorescent
vertex act as diagonal matrices: their RGB value v becomes per-band albedos
a_k = (F v)_k / (F 1)_k, with F the map from RGB light to basis coefficients (for
``basis="rgb"`` simply v). Emitters contribute R·c: for emitters whose radiance is a
``fluo_illuminant`` the coefficients of its spectrum (including the UV band, so a UV-only
lamp still excites fluorescence), for others F times their RGB radiance. Reduced matrices
have negative entries (the dual basis has negative lobes), so coefficients along a path
are signed and kept so; only the final linear sRGB of each sample is clipped at zero
(out-of-gamut colours such as a saturated 520 nm emission have negative sRGB red, which
Mitsuba's RGB film would otherwise warn about on every sample). This clips a little
energy from colours outside the sRGB gamut, which an sRGB image cannot show anyway.

**Wavelength shifting.** The camera path carries four hero wavelengths, each with its
own throughput. At a fluorescent vertex, each wavelength λo (the one travelling
towards the camera) decides on its own between the elastic event (λ kept) and a shift
to an excitation wavelength λi < λo sampled by the material; directions stay shared.
Emitter sampling and later bounces then see the shifted wavelengths; the film still
receives the camera wavelengths.

*Why the estimator is unbiased.* For a fixed λo the vertex must estimate
``f_e(λo) L(λo) + ∫_R f_fl(λi, λo) L(λi) dλi`` (elastic plus reradiation; L is the
incident radiance, which is zero outside R). Let ``w_e`` be the elastic albedo and
``w_f`` the reradiated albedo reaching λo from excitations in R (both from the
material). We pick the elastic event with probability ``p_e = w_e / (w_e + w_f)``
and weight it by ``1/p_e``, or the shift with probability ``1 − p_e``, sampling λi
with density ``p(λi)`` over R and weighting by ``1/((1 − p_e) p(λi))``. The expectation
of either branch's weighted integrand is its term above, and their sum is the whole.
``p_e`` is positive exactly where ``f_e`` is and ``1 − p_e`` exactly where the shift
integrand is, so no contribution is skipped. After the choice the vertex is an
ordinary (wavelength-changing) BSDF: next-event estimation and BSDF sampling estimate
the incident radiance L(λi, ω) with the usual MIS weights, which do not depend on
wavelength. Each hero wavelength is an independent estimator of its camera
wavelength's radiance, so the film's wavelength weights stay valid.

Spatially varying fluorescence (``fluo_jung`` with a ``color`` texture) is looked up
per vertex through the bispectral interface's ``fluorescence_at(si)``: each vertex
uses its own texel's model and intersects its excitation band with R.

Fluorescent materials may be wrapped in ``twosided``, ``blendbsdf`` and ``mask``
(nested too): at each vertex the integrator resolves the wrapper to the BSDF that acts
there — ``twosided``: the front or back child, with the local frame mirrored for the
back side exactly as ``twosided`` does; ``blendbsdf``: child 1 with probability w(si),
else child 0; ``mask``: the nested BSDF with probability opacity(si), else a null
(pass-through) interaction, as ``mask`` samples it — and treats that child as an
unwrapped material. The selections are unbiased: renders equal the wrapper's within
noise. Any other BSDF around a fluorescent one (``bumpmap``, ``normalmap``, ...) is
refused with an error at render start (the first access the integrator has to the
scene) rather than rendered without its fluorescence. Mitsuba's own integrators
(``path``, ...) render only the elastic part of fluorescent materials, and say so once
per scene.

.. tabs::
    .. code-tab:: xml

        <integrator type="fluo_path">
            <integer name="max_depth" value="8"/>
        </integrator>
*/
template <typename Float, typename Spectrum>
class FluoPath final : public MonteCarloIntegrator<Float, Spectrum> {
public:
    MI_IMPORT_BASE(MonteCarloIntegrator, m_max_depth, m_rr_depth, m_hide_emitters)
    MI_IMPORT_TYPES(Scene, Sensor, Sampler, Medium, Emitter, EmitterPtr, BSDF, BSDFPtr, Texture, Shape)

    static constexpr const char *Plugin = "fluo_path";
    /// Allowed range of `lambda_min`, nm.
    static constexpr double LambdaMinLo = 200.0, LambdaMinHi = 360.0;

    FluoPath(const Properties &props) : Base(props) {
        m_lambda_min = fluo_detail::get_float(Plugin, props, "lambda_min", 300.0);
        if (!(m_lambda_min >= LambdaMinLo && m_lambda_min <= LambdaMinHi))
            Throw("%s: invalid parameter \"lambda_min\" = %f: valid range is [%.0f, %.0f] nm",
                  Plugin, m_lambda_min, LambdaMinLo, LambdaMinHi);
        std::string basis = props.has_property("basis")
                                ? std::string(props.get<std::string_view>("basis")) : "x7";
        std::string method = props.has_property("method")
                                 ? std::string(props.get<std::string_view>("method")) : "ours";
        m_transport = fluo_detail::rust_call(Plugin, [&] { return fluo::transport_new(basis, method); });
        m_k = fluo::transport_size(*m_transport);
        if (m_k > KMax)
            Throw("%s: basis \"%s\" has %zu bands, at most %zu are supported", Plugin, basis, m_k, KMax);
        fluo::transport_output(*m_transport, rust::Slice<double>(m_output.data(), 3 * m_k));
        fluo::transport_from_rgb(*m_transport, rust::Slice<double>(m_from_rgb.data(), 3 * m_k));
        fluo::transport_white(*m_transport, rust::Slice<double>(m_white.data(), m_k));
    }

    using Base::render;
    TensorXf render(Scene *scene, Sensor *sensor, UInt32 seed, uint32_t spp, bool develop,
                    bool evaluate) override {
        prepare(scene);
        return Base::render(scene, sensor, seed, spp, develop, evaluate);
    }

    std::pair<Spectrum, Bool> sample(const Scene *scene, Sampler *sampler,
                                     const RayDifferential3f &ray_, const Medium * /* medium */,
                                     Float * /* aovs */, Bool active) const override {
        if (unlikely(m_max_depth == 0))
            return { 0.f, false };
        if constexpr (is_rgb_v<Spectrum>) {
            if (m_active)
                return sample_reduced(scene, sampler, ray_, active);
        }

        // Scalar port of Mitsuba's path.cpp (v3.8.0); fluorescence is inserted where
        // the BSDF is known. Without fluorescent vertices the random numbers drawn
        // and the arithmetic are the same.
        Ray3f ray              = Ray3f(ray_);
        Spectrum throughput    = 1.f;
        Spectrum result        = 0.f;
        Float eta              = 1.f;
        UInt32 depth           = 0;
        Mask valid_ray         = !m_hide_emitters && (scene->environment() != nullptr);
        Interaction3f prev_si  = dr::zeros<Interaction3f>();
        Float prev_bsdf_pdf    = 1.f;
        Bool prev_bsdf_delta   = true;
        BSDFContext bsdf_ctx;

        PreliminaryIntersection3f pi = camera_intersection(scene, ray, active);

        while (active) {
            SurfaceInteraction3f si = pi.compute_surface_interaction(ray, +RayFlags::All);

            // ---------------------- Direct emission ----------------------
            if (si.emitter(scene) != nullptr) {
                auto [emitter, le, mis_bsdf] = hit_emission(scene, si, prev_si, prev_bsdf_pdf, prev_bsdf_delta);
                result = spec_fma(throughput, le * mis_bsdf, result);
            }

            Bool active_next = (depth + 1 < m_max_depth) && si.is_valid();
            if (!active_next) {
                valid_ray |= (si.emitter(scene) != nullptr) && !m_hide_emitters;
                break;
            }

            BSDFPtr bsdf = si.bsdf(ray);
            if (!m_wrappers.empty())
                bsdf = resolve(bsdf, si, sampler);

            // ---------------------- Fluorescence ----------------------
            // Choose, per hero wavelength, the elastic event or a shift λo -> λi.
            Transition tr;
            const Entry *fl = m_active ? find(bsdf) : nullptr;
            if (fl)
                tr = choose_transitions(*fl, si, sampler);

            // ---------------------- Emitter sampling ----------------------
            Mask active_em = active_next && has_flag(bsdf->flags(), BSDFFlags::Smooth);
            DirectionSample3f ds = dr::zeros<DirectionSample3f>();
            Spectrum em_weight = dr::zeros<Spectrum>();
            Vector3f wo = dr::zeros<Vector3f>();
            if (active_em) {
                std::tie(ds, em_weight) = scene->sample_emitter_direction(si, sampler->next_2d(), true, active_em);
                active_em &= (ds.pdf != 0.f);
                wo = si.to_local(ds.d);
            }

            // ------ Evaluate BSDF * cos(theta) and sample direction -------
            Float sample_1 = sampler->next_1d();
            Point2f sample_2 = sampler->next_2d();
            auto [bsdf_val, bsdf_pdf, bsdf_sample, bsdf_weight] =
                bsdf->eval_pdf_sample(bsdf_ctx, si, wo, sample_1, sample_2);

            if (fl) {
                apply_transitions(*fl, tr, si, wo, bsdf_val);
                if (bsdf_sample.pdf > 0.f) {
                    bsdf_weight *= bsdf_sample.pdf; // back to BSDF value (elastic slots)
                    apply_transitions(*fl, tr, si, bsdf_sample.wo, bsdf_weight);
                    bsdf_weight /= bsdf_sample.pdf;
                }
            }

            // --------------- Emitter sampling contribution ----------------
            if (active_em) {
                bsdf_val = si.to_world_mueller(bsdf_val, -wo, si.wi);
                Float mis_em = dr::select(ds.delta, 1.f, mis_weight(ds.pdf, bsdf_pdf));
                result = spec_fma(throughput, bsdf_val * em_weight * mis_em, result);
            }

            // ---------------------- BSDF sampling ----------------------
            bsdf_weight = si.to_world_mueller(bsdf_weight, -bsdf_sample.wo, si.wi);
            ray = si.spawn_ray(si.to_world(bsdf_sample.wo)); // carries the shifted wavelengths

            throughput *= bsdf_weight;
            eta *= bsdf_sample.eta;
            valid_ray |= active && si.is_valid() && !has_flag(bsdf_sample.sampled_type, BSDFFlags::Null);

            prev_si = Interaction3f(si);
            prev_bsdf_pdf = bsdf_sample.pdf;
            prev_bsdf_delta = has_flag(bsdf_sample.sampled_type, BSDFFlags::Delta);

            // -------------------- Stopping criterion ---------------------
            if (si.is_valid())
                depth += 1;
            Float throughput_max = dr::max(unpolarized_spectrum(throughput));
            Float rr_prob = dr::minimum(throughput_max * dr::square(eta), .95f);
            Mask rr_active = depth >= m_rr_depth, rr_continue = sampler->next_1d() < rr_prob;
            if (rr_active)
                throughput *= dr::rcp(rr_prob);
            active = active_next && (!rr_active || rr_continue) && (throughput_max != 0.f);

            pi = scene->ray_intersect_preliminary(ray, false, false, 0, 0, active);
        }

        return { dr::select(valid_ray, result, 0.f), valid_ray };
    }

    std::string to_string() const override {
        std::ostringstream oss;
        oss << "FluoPath[" << std::endl
            << "  max_depth = " << m_max_depth << "," << std::endl
            << "  rr_depth = " << m_rr_depth << "," << std::endl
            << "  lambda_min = " << m_lambda_min << "," << std::endl
            << "  basis = " << std::string(fluo::transport_name(*m_transport)) << " (K = " << m_k << ")," << std::endl
            << "  fluorescent_bsdfs = " << m_entries.size() << "," << std::endl
            << "  excitation_range = [" << m_range.lo << ", " << m_range.hi << "]" << std::endl
            << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(FluoPath)

private:
    static constexpr size_t N = dr::size_v<Spectrum> == 4 ? 4 : 1;

    /// A fluorescent BSDF of the scene with the excitation range it can use.
    struct Entry {
        const BSDF *bsdf;
        const BispectralBSDF<Float, Spectrum> *bispectral;
        const fluo::Fluorescence *model;
        fluo::Range range;
        /// Spatially varying: the model and its range are looked up per vertex.
        bool varies = false;
        const fluo::ReducedModel *reduced = nullptr; // scalar_rgb only
    };

    /// Per-wavelength choice at a fluorescent vertex.
    struct Transition {
        std::array<bool, 4> shifted{};
        std::array<double, 4> lambda_o{}, lambda_i{};
        std::array<float, 4> scale{};
        /// The model at this vertex (per texel for spatially varying materials).
        const fluo::Fluorescence *model = nullptr;
    };

    /// First intersection of a camera ray, skipping area emitters when they are hidden
    /// (as path.cpp does at depth 0).
    PreliminaryIntersection3f camera_intersection(const Scene *scene, const Ray3f &ray, Mask active) const {
        PreliminaryIntersection3f pi = scene->ray_intersect_preliminary(ray, true, false, 0, 0, active);
        if (m_hide_emitters) {
            Mask skip = pi.is_valid() && (pi.shape->emitter() != nullptr) && active;
            if (skip) {
                SurfaceInteraction3f si = pi.compute_surface_interaction(ray, +RayFlags::Minimal, skip);
                pi = Base::skip_area_emitters(scene, si.spawn_ray(ray.d), true, skip);
            }
        }
        return pi;
    }

    /// Emission found by a BSDF-sampled ray: (emitter, radiance, MIS weight), as in path.cpp.
    std::tuple<const Emitter *, Spectrum, Float>
    hit_emission(const Scene *scene, const SurfaceInteraction3f &si, const Interaction3f &prev_si,
                 Float prev_bsdf_pdf, Bool prev_bsdf_delta) const {
        DirectionSample3f ds(scene, si, prev_si);
        Float em_pdf = 0.f;
        if (!prev_bsdf_delta)
            em_pdf = scene->pdf_emitter_direction(prev_si, ds, !prev_bsdf_delta);
        return { ds.emitter, ds.emitter->eval(si, prev_bsdf_pdf > 0.f), mis_weight(prev_bsdf_pdf, em_pdf) };
    }

    /// Power heuristic, as in path.cpp (non-finite weights become 0).
    Float mis_weight(Float pdf_a, Float pdf_b) const {
        pdf_a *= pdf_a;
        pdf_b *= pdf_b;
        Float w = pdf_a / (pdf_a + pdf_b);
        return dr::select(dr::isfinite(w), w, 0.f);
    }

    /// a * b + c as a fused multiply-add, as in path.cpp (unpolarized variants only).
    Spectrum spec_fma(const Spectrum &a, const Spectrum &b, const Spectrum &c) const {
        return dr::fmadd(a, b, c);
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

    /// A supported BSDF wrapper around fluorescent materials (see the doc comment).
    struct Wrapper {
        enum Kind { TwoSided, Blend, Mask };
        const BSDF *bsdf;
        Kind kind;
        const BSDF *child[2]{};      // front/back, bsdf_0/bsdf_1, or nested/null
        const Texture *weight = nullptr; // blend weight or mask opacity
    };

    /// Direct children of an object as (name, object), in traverse order.
    struct Children : TraversalCallback {
        std::vector<std::pair<std::string, Object *>> list;
        void put_value(std::string_view, void *, uint32_t, const std::type_info &) override {}
        void put_object(std::string_view name, Object *o, uint32_t) override {
            if (o)
                list.emplace_back(std::string(name), o);
        }
    };

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

    /// Mark every bispectral material as transported by fluo_path, and record the
    /// wrappers around fluorescent ones; refuse wrappers it cannot see through.
    void scan_wrappers(const Collector &c) {
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
            if (cls != "TwoSidedBRDF" && cls != "BlendBSDF" && cls != "MaskBSDF")
                Throw("%s: a fluorescent material is wrapped in a \"%s\" BSDF, which fluo_path cannot "
                      "see through (its fluorescence would be lost). Supported wrappers: twosided, "
                      "blendbsdf, mask; use the fluorescent material directly or inside one of those.",
                      Plugin, std::string(cls));
            Wrapper w{ bsdf, cls == "TwoSidedBRDF" ? Wrapper::TwoSided
                             : cls == "BlendBSDF" ? Wrapper::Blend : Wrapper::Mask };
            for (auto &[name, child] : kids.list) {
                auto *cb = dynamic_cast<BSDF *>(child);
                if (cb && (name == "brdf_0" || name == "bsdf_0" || name == "nested_bsdf"))
                    w.child[0] = cb;
                else if (cb && (name == "brdf_1" || name == "bsdf_1"))
                    w.child[1] = cb;
                else if (name == "weight" || name == "opacity")
                    w.weight = dynamic_cast<Texture *>(child);
            }
            if (w.kind == Wrapper::TwoSided && !w.child[1])
                w.child[1] = w.child[0]; // one child: used on both sides
            if (w.kind == Wrapper::Mask)
                w.child[1] = null_bsdf();
            if (!w.child[0] || !w.child[1] || (w.kind != Wrapper::TwoSided && !w.weight))
                Throw("%s: cannot read the children of the \"%s\" BSDF around a fluorescent material",
                      Plugin, std::string(cls));
            m_wrappers.push_back(w);
        }
    }

    /// The BSDF that acts at si: wrappers (twosided, blendbsdf; nested) resolved to
    /// the child acting at this hit. For a twosided back side the local frame is
    /// mirrored (n -> -n), as twosided mirrors wi and wo.
    BSDFPtr resolve(BSDFPtr bsdf, SurfaceInteraction3f &si, Sampler *sampler) const {
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
            } else {
                Float opacity = dr::clip(w->weight->eval_1(si, true), 0.f, 1.f);
                bsdf = w->child[sampler->next_1d() < opacity ? 0 : 1];
            }
        }
        return bsdf;
    }

    /// Mitsuba's `null` BSDF (pass-through, sampled as a Null/Delta event), created once:
    /// the transparent part of a `mask`.
    const BSDF *null_bsdf() {
        if (!m_null)
            m_null = PluginManager::instance()->create_object<BSDF>(Properties("null"));
        return m_null.get();
    }

    const Entry *find(const BSDF *bsdf) const {
        for (const Entry &e : m_entries)
            if (e.bsdf == bsdf)
                return &e;
        return nullptr;
    }

    static fluo::Vec3 vec(const Vector3f &v) { return fluo::Vec3{ v.x(), v.y(), v.z() }; }

    /// Pick elastic or shifted per wavelength (see the unbiasedness note in the doc
    /// comment) and move si.wavelengths to the excitation wavelengths.
    Transition choose_transitions(const Entry &e, SurfaceInteraction3f &si, Sampler *sampler) const {
        Transition tr;
        if constexpr (is_spectral_v<Spectrum>) {
            tr.model = e.model;
            fluo::Range range = e.range;
            if (e.varies) {
                tr.model = e.bispectral->fluorescence_at(si);
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
                double wf = std::max(0.0, fluo::fluo_shift_albedo(*tr.model, wi, lo, range));
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
    void apply_transitions(const Entry & /* e */, const Transition &tr, const SurfaceInteraction3f &si,
                           const Vector3f &wo, Spectrum &value) const {
        if constexpr (is_spectral_v<Spectrum>) {
            if (!tr.model)
                return; // all elastic at this vertex
            fluo::Vec3 wi = vec(si.wi), o = vec(wo);
            for (size_t j = 0; j < N; ++j) {
                if (tr.shifted[j])
                    value[j] = (float) fluo::fluo_reradiation(*tr.model, wi, o, tr.lambda_i[j], tr.lambda_o[j]);
                value[j] *= tr.scale[j];
            }
        }
    }

    /// Scan the scene once per render: fluorescent BSDFs and emitter spectral ranges.
    void prepare(Scene *scene) {
        m_entries.clear();
        m_wrappers.clear();
        m_active = false;
        if constexpr (is_rgb_v<Spectrum>) {
            prepare_reduced(scene);
            return;
        } else {
            // Where can light exist? The union of the emitters' radiance spectra.
            double lo = 1e30, hi = -1e30;
            for (const auto &emitter : scene->emitters()) {
                Collector c;
                c.visit(const_cast<Emitter *>(emitter.get()));
                bool found = false;
                for (Object *o : c.objects)
                    if (auto *tex = dynamic_cast<Texture *>(o)) {
                        ScalarVector2f r = tex->wavelength_range();
                        lo = std::min(lo, (double) r.x());
                        hi = std::max(hi, (double) r.y());
                        found = true;
                    }
                if (!found) {
                    lo = std::min(lo, (double) MI_CIE_MIN);
                    hi = std::max(hi, (double) MI_CIE_MAX);
                }
            }
            if (scene->emitters().empty())
                return;
            lo = std::max(lo, m_lambda_min);

            // Fluorescent BSDFs anywhere in the scene graph.
            Collector c;
            for (const auto &shape : scene->shapes())
                c.visit(const_cast<Shape *>(shape.get()));
            scan_wrappers(c);
            std::vector<Entry> candidates;
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
                if (e.range.lo < e.range.hi)
                    m_entries.push_back(e);
            }
            m_active = !m_entries.empty();
        }
    }

    // ---------------- reduced (matrix-throughput) transport, scalar_rgb ----------------
    static constexpr size_t KMax = 7;
    using Row3 = std::array<double, 3 * KMax>;      // 3×K, row major
    using Square = std::array<double, KMax * KMax>; // K×K, row major
    using Coeffs = std::array<double, KMax>;

    struct EmitterSource {
        const Emitter *emitter;
        Coeffs coeffs;   // basis coefficients of its spectrum (as the texture is defined)
        double luminance; // luminance of the texture's RGB, to rescale by the emitter's
    };

    static double luminance_of(const Spectrum &v) {
        if constexpr (is_rgb_v<Spectrum>)
            return 0.212671 * v[0] + 0.715160 * v[1] + 0.072169 * v[2];
        else
            return 0.0;
    }

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

    /// Per-band albedos of an RGB value as a diagonal matrix.
    void diagonal_of(const Spectrum &v, Square &m) const {
        m.fill(0.0);
        if constexpr (is_rgb_v<Spectrum>) {
            double mean = (v[0] + v[1] + v[2]) / 3.0;
            for (size_t k = 0; k < m_k; ++k) {
                double num = m_from_rgb[k * 3] * v[0] + m_from_rgb[k * 3 + 1] * v[1] +
                             m_from_rgb[k * 3 + 2] * v[2];
                m[k * m_k + k] = std::abs(m_white[k]) > 1e-12 ? num / m_white[k] : mean;
            }
        }
    }

    /// The K×K vertex matrix of a fluorescent BSDF for direction wo (value · cos).
    void fluorescent_matrix(const Entry &e, const SurfaceInteraction3f &si, const Vector3f &wo,
                            Square &m) const {
        if (fluo::reduced_includes_elastic(*e.reduced))
            m.fill(0.0);
        else
            diagonal_of(Spectrum(e.bispectral->eval_elastic(si, wo)), m);
        Square r{};
        fluo::reduced_reradiation(*e.reduced, vec(si.wi), vec(wo),
                                  rust::Slice<double>(r.data(), m_k * m_k));
        for (size_t i = 0; i < m_k * m_k; ++i)
            m[i] += r[i];
    }

    /// R ← R · M · s
    void multiply(Row3 &r, const Square &m, double s) const {
        Row3 out{};
        for (size_t row = 0; row < 3; ++row)
            for (size_t j = 0; j < m_k; ++j) {
                double acc = 0.0;
                for (size_t k = 0; k < m_k; ++k)
                    acc += r[row * m_k + k] * m[k * m_k + j];
                out[row * m_k + j] = acc * s;
            }
        r = out;
    }

    /// result += R · c · s
    void accumulate(Color3f &result, const Row3 &r, const Coeffs &c, double s) const {
        for (size_t row = 0; row < 3; ++row) {
            double acc = 0.0;
            for (size_t k = 0; k < m_k; ++k)
                acc += r[row * m_k + k] * c[k];
            result[row] += (float) (acc * s);
        }
    }

    /// R = diag(t) · m_output: the 3×K throughput of an RGB throughput t.
    Row3 rows_scaled(const Color3f &t) const {
        Row3 r = m_output;
        for (size_t row = 0; row < 3; ++row)
            for (size_t k = 0; k < m_k; ++k)
                r[row * m_k + k] *= (double) t[row];
        return r;
    }

    /// scalar_rgb with fluorescent materials: the path loop of sample() with a 3×K
    /// throughput matrix (adjoint reduced transport, see the doc comment). Until a path
    /// meets its first fluorescent vertex it carries Mitsuba's RGB throughput and does
    /// exactly what `path` does (native materials and lights render as natively); the
    /// first fluorescent vertex turns the RGB throughput t into R = diag(t)·m_output·M.
    std::pair<Spectrum, Bool> sample_reduced(const Scene *scene, Sampler *sampler,
                                             const RayDifferential3f &ray_, Bool active) const {
        if constexpr (!is_rgb_v<Spectrum>) {
            return { 0.f, false };
        } else {
            Ray3f ray = Ray3f(ray_);
            Row3 R{};
            Color3f t = 1.f;       // RGB throughput while no fluorescent vertex was met
            bool reduced = false;  // whether R (not t) carries the throughput
            Color3f result = 0.f;
            Float eta = 1.f;
            UInt32 depth = 0;
            Mask valid_ray = !m_hide_emitters && (scene->environment() != nullptr);
            Interaction3f prev_si = dr::zeros<Interaction3f>();
            Float prev_bsdf_pdf = 1.f;
            Bool prev_bsdf_delta = true;
            BSDFContext bsdf_ctx;
            Square m{};

            PreliminaryIntersection3f pi = camera_intersection(scene, ray, active);

            while (active) {
                SurfaceInteraction3f si = pi.compute_surface_interaction(ray, +RayFlags::All);

                if (si.emitter(scene) != nullptr) {
                    auto [emitter, le, mis_bsdf] = hit_emission(scene, si, prev_si, prev_bsdf_pdf, prev_bsdf_delta);
                    if (reduced)
                        accumulate(result, R, emitter_coefficients(emitter, le), mis_bsdf);
                    else
                        result = spec_fma(t, le * mis_bsdf, result);
                }

                Bool active_next = (depth + 1 < m_max_depth) && si.is_valid();
                if (!active_next) {
                    valid_ray |= (si.emitter(scene) != nullptr) && !m_hide_emitters;
                    break;
                }

                BSDFPtr bsdf = si.bsdf(ray);
                if (!m_wrappers.empty())
                    bsdf = resolve(bsdf, si, sampler);
                const Entry *fl = find(bsdf);

                // ---------------------- Emitter sampling ----------------------
                Mask active_em = active_next && has_flag(bsdf->flags(), BSDFFlags::Smooth);
                if (active_em) {
                    auto [ds, em_weight] = scene->sample_emitter_direction(si, sampler->next_2d(), true, active_em);
                    if (ds.pdf != 0.f) {
                        Vector3f wo = si.to_local(ds.d);
                        if (fl) {
                            fluorescent_matrix(*fl, si, wo, m);
                            Float mis_em = dr::select(ds.delta, 1.f, mis_weight(ds.pdf, bsdf->pdf(bsdf_ctx, si, wo)));
                            Row3 rm = reduced ? R : rows_scaled(t);
                            multiply(rm, m, 1.0);
                            accumulate(result, rm, emitter_coefficients(ds.emitter, em_weight), mis_em);
                        } else {
                            auto [val, bsdf_pdf] = bsdf->eval_pdf(bsdf_ctx, si, wo);
                            Float mis_em = dr::select(ds.delta, 1.f, mis_weight(ds.pdf, bsdf_pdf));
                            if (reduced) {
                                diagonal_of(val, m);
                                Row3 rm = R;
                                multiply(rm, m, 1.0);
                                accumulate(result, rm, emitter_coefficients(ds.emitter, em_weight), mis_em);
                            } else {
                                result = spec_fma(t, val * em_weight * mis_em, result);
                            }
                        }
                    }
                }

                // ---------------------- BSDF sampling ----------------------
                Float sample_1 = sampler->next_1d();
                Point2f sample_2 = sampler->next_2d();
                auto [bs, weight] = bsdf->sample(bsdf_ctx, si, sample_1, sample_2);
                if (fl) {
                    if (!reduced)
                        R = rows_scaled(t);
                    reduced = true;
                    if (bs.pdf > 0.f) {
                        fluorescent_matrix(*fl, si, bs.wo, m);
                        multiply(R, m, 1.0 / bs.pdf);
                    } else {
                        multiply(R, Square{}, 0.0);
                    }
                } else if (reduced) {
                    diagonal_of(weight, m);
                    multiply(R, m, 1.0);
                } else {
                    t *= weight;
                }
                ray = si.spawn_ray(si.to_world(bs.wo));
                eta *= bs.eta;
                valid_ray |= active && si.is_valid() && !has_flag(bs.sampled_type, BSDFFlags::Null);
                prev_si = Interaction3f(si);
                prev_bsdf_pdf = bs.pdf;
                prev_bsdf_delta = has_flag(bs.sampled_type, BSDFFlags::Delta);

                if (si.is_valid())
                    depth += 1;
                double throughput_max = 0.0;
                if (reduced) {
                    for (size_t i = 0; i < 3 * m_k; ++i)
                        throughput_max = std::max(throughput_max, std::abs(R[i]));
                } else {
                    throughput_max = (double) dr::max(t);
                }
                Float rr_prob = dr::minimum((Float) throughput_max * dr::square(eta), .95f);
                Mask rr_active = depth >= m_rr_depth, rr_continue = sampler->next_1d() < rr_prob;
                if (rr_active) {
                    for (size_t i = 0; i < 3 * m_k; ++i)
                        R[i] /= rr_prob;
                    t /= rr_prob;
                }
                active = active_next && (!rr_active || rr_continue) && (throughput_max != 0.0);
                pi = scene->ray_intersect_preliminary(ray, false, false, 0, 0, active);
            }
            // Out-of-gamut colours (a saturated 520 nm emission has negative linear sRGB
            // red) are clipped here, per sample, as an sRGB film must store them; along
            // the path the coefficients stay signed.
            result = dr::maximum(result, 0.f);
            return { dr::select(valid_ray, Spectrum(result), 0.f), valid_ray };
        }
    }

    /// scalar_rgb: reduce every fluorescent BSDF for the transport basis, and find the
    /// emitters whose radiance has a known spectrum.
    void prepare_reduced(Scene *scene) {
        m_reduced.clear();
        m_sources.clear();
        Collector c;
        for (const auto &shape : scene->shapes())
            c.visit(const_cast<Shape *>(shape.get()));
        scan_wrappers(c);
        for (Object *o : c.objects) {
            auto *bsdf = dynamic_cast<BSDF *>(o);
            auto *bisp = dynamic_cast<BispectralBSDF<Float, Spectrum> *>(o);
            // Spatially varying materials (fluo_jung with a colour texture) stay plain
            // BSDFs here: their RGB value is the colour the upsampling cube reproduces.
            if (!bsdf || !bisp || !bisp->fluorescence() || bisp->fluorescence_varies())
                continue;
            const fluo::Fluorescence *model = bisp->fluorescence();
            m_reduced.push_back(fluo_detail::rust_call(
                Plugin, [&] { return fluo::reduced_new(*model, *m_transport); }));
            m_entries.push_back(Entry{ bsdf, bisp, model, fluo::fluo_excitation_range(*model), false,
                                       &*m_reduced.back() });
        }
        bool warned_uv = m_uv_warned == scene; // one warning per scene
        for (const auto &emitter : scene->emitters()) {
            Collector ce;
            ce.visit(const_cast<Emitter *>(emitter.get()));
            for (Object *o : ce.objects)
                if (auto *src = dynamic_cast<SpectralSource *>(o)) {
                    EmitterSource es{ emitter.get(), {}, 0.0 };
                    fluo::illuminant_coefficients(src->illuminant(), *m_transport,
                                                  rust::Slice<double>(es.coeffs.data(), m_k));
                    es.luminance = src->rgb_luminance();
                    m_sources.push_back(es);
                    if (!warned_uv && !m_entries.empty() && fluo::illuminant_is_mostly_uv(src->illuminant())) {
                        warned_uv = true;
                        m_uv_warned = scene;
                        Log(Warn, "%s (scalar_rgb): emitter %s is mostly ultraviolet; reduced transport "
                                  "carries it in one UV band, which can misstate UV-excited fluorescence "
                                  "several times over (a narrow 365 nm lamp: ~5x too dark, see `fluo-rs "
                                  "saturated-report`). Render UV-lit scenes in scalar_spectral where that "
                                  "matters.", Plugin,
                            emitter->id().empty() ? std::string(emitter->class_name()) : emitter->id());
                    }
                    break;
                }
        }
        m_active = !m_entries.empty();
    }

    double m_lambda_min;
    rust::Box<fluo::TransportBasis> m_transport = fluo_detail::rust_call(
        Plugin, [] { return fluo::transport_new("rgb", "ours"); });
    size_t m_k = 3;
    Row3 m_output{}, m_from_rgb{};
    Coeffs m_white{};
    std::vector<rust::Box<fluo::ReducedModel>> m_reduced;
    ref<BSDF> m_null; ///< see null_bsdf()
    const Scene *m_uv_warned = nullptr; ///< the scene last warned of a UV emitter
    std::vector<EmitterSource> m_sources;
    std::vector<Entry> m_entries;
    std::vector<Wrapper> m_wrappers;
    fluo::Range m_range{ 0, 0 };
    bool m_active = false;
};

static const bool fluo_path_registered =
    (fluo_detail::register_scalar_plugin<FluoPath>("fluo_path", ObjectType::Integrator), true);

NAMESPACE_END(mitsuba)
