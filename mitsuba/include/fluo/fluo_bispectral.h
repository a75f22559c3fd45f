// The bispectral interface every fluorescent BSDF implements next to Mitsuba's BSDF
// interface (BispectralBSDF), which fluo_path and fluo_volpath reach per lane through
// dr::dispatch in every variant, the elastic/shift choice at a fluorescent vertex
// (ShiftChoice, SurfaceShift), and the registration of a plugin class template for every
// variant fluo serves.
//
// Dr.Jit cannot trace calls into Rust, so Rust runs at load time and in
// parameters_changed() only: it validates the parameters and bakes tables (absorption CDFs,
// reduced matrices, RGB parts), which the plugins evaluate per lane with Dr.Jit types in
// every variant (the closed forms and table lookups are fluo_forms.h).
#pragma once

#include <mitsuba/core/distr_1d.h>
#include <mitsuba/core/plugin.h>
#include <mitsuba/render/bsdf.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <optional>
#include <string>
#include <tuple>
#include <typeinfo>
#include <vector>

#include "fluo_common.h"
#include "fluo_forms.h"
#include "fluo_lambertian.h"

NAMESPACE_BEGIN(mitsuba)
NAMESPACE_BEGIN(fluo_detail)

/// Register T<Float, Spectrum> as plugin `name` in `variant`.
template <template <typename, typename> class T, typename Float, typename Spec>
void register_variant(const char *name, const char *variant, ObjectType type) {
    PluginManager::instance()->register_plugin(
        name, variant, type, [](void *, const Properties &p) -> ref<Object> { return new T<Float, Spec>(p); },
        nullptr, nullptr);
}

/// Register plugin class template T, once, for every variant it serves: the rgb, spectral
/// and spectral_polarized variants of scalar, llvm_ad and cuda_ad (the CUDA ones compile
/// without a GPU and run where one is present); every other variant of
/// the wheel gets a factory that names the plugin and the variant (register_unavailable).
template <template <typename, typename> class T> void register_plugin(const char *name, ObjectType type) {
    fluo::note_plugin(name, type == ObjectType::BSDF ? "bsdf"
                            : type == ObjectType::Integrator ? "integrator"
                            : type == ObjectType::Medium     ? "medium"
                                                             : "texture",
                      true);
    register_unavailable(name, type);
    using LFloat = dr::DiffArray<JitBackend::LLVM, float>;
    using CFloat = dr::DiffArray<JitBackend::CUDA, float>;
    register_variant<T, float, Color<float, 3>>(name, "scalar_rgb", type);
    register_variant<T, float, Spectrum<float, 4>>(name, "scalar_spectral", type);
    register_variant<T, float, MuellerMatrix<Spectrum<float, 4>>>(name, "scalar_spectral_polarized", type);
    register_variant<T, LFloat, Color<LFloat, 3>>(name, "llvm_ad_rgb", type);
    register_variant<T, LFloat, Spectrum<LFloat, 4>>(name, "llvm_ad_spectral", type);
    register_variant<T, LFloat, MuellerMatrix<Spectrum<LFloat, 4>>>(name, "llvm_ad_spectral_polarized", type);
    register_variant<T, CFloat, Color<CFloat, 3>>(name, "cuda_ad_rgb", type);
    register_variant<T, CFloat, Spectrum<CFloat, 4>>(name, "cuda_ad_spectral", type);
    register_variant<T, CFloat, MuellerMatrix<Spectrum<CFloat, 4>>>(name, "cuda_ad_spectral_polarized", type);
}

/// dr::dispatch exists for JIT pointer arrays only; a scalar pointer is called directly.
template <typename Ptr, typename Func, typename... Args>
auto dispatch_any(const Ptr &self, const Func &func, const Args &...args) {
    if constexpr (dr::is_jit_v<Ptr>)
        return dr::dispatch(self, func, args...);
    else
        return func(self, args...);
}

/// A differentiable scalar parameter's value after an update through mi.traverse, read on
/// the host: it must still hold one value (an array of several would otherwise render
/// with its first, or fail inside Dr.Jit at render time). `current` (the configuration's
/// value, in double precision) is kept where the member still holds it in single precision,
/// so a parameter the update did not touch (or a refused update, undone) leaves the
/// material exactly as loaded.
template <typename Float> double updated_param(const char *plugin, const char *name, const Float &v, double current) {
    if (dr::width(v) != 1) // (always 1 in the scalar variants)
        Throw("%s: parameter \"%s\" must hold one value, got an array of %zu", plugin, name, (size_t) dr::width(v));
    double x = (double) dr::slice(dr::detach(v), 0);
    return x == (double) (float) current ? current : x;
}

/// ∂f/∂θ of a host computation f (values in a vector) by central differences with step h,
/// (f(θ + h) − f(θ − h))/2h, one-sided where a step is refused: `at(δ)` evaluates f at θ + δ
/// and returns nothing outside the parameter's range. Nothing if neither step is allowed.
/// (The RGB reductions' derivatives with respect to parameters baked into them.)
template <typename At> std::optional<std::vector<double>> central_difference(double h, At &&at) {
    std::optional<std::vector<double>> hi = at(h), lo = at(-h);
    double span = (hi ? h : 0.0) + (lo ? h : 0.0);
    if (!hi)
        hi = at(0.0);
    if (!lo)
        lo = at(0.0);
    if (!hi || !lo || !(span > 0.0) || hi->size() != lo->size())
        return std::nullopt;
    for (size_t j = 0; j < hi->size(); ++j)
        (*hi)[j] = ((*hi)[j] - (*lo)[j]) / span;
    return hi;
}

/// x / detach(x): value exactly 1 (also where x is 0), derivative ∂x/x. A constant where x
/// carries no gradient (every primal kernel: no division traced), and 1 rather than the
/// quotient's own value where it does (CUDA's approximate division is not exactly 1, and
/// path replay must reproduce the primal's throughput, roulette included).
template <typename Value> Value relative(const Value &x) {
    if constexpr (dr::is_diff_v<Value>) {
        if (dr::grad_enabled(x)) {
            Value d = dr::detach(x);
            Value q = x / dr::select(d != 0.f, d, 1.f);
            return dr::select(d != 0.f, q - dr::detach(q) + 1.f, 1.f);
        }
    }
    return Value(1.f);
}

/// Path replay: the relative derivative of a BSDF sample's weight at its detached direction,
/// its value's or, where it passed a null lobe, the null transmission's (a mask's
/// 1 − opacity: the value there is 0, with no derivative).
template <typename BSDFPtr_, typename Context, typename Interaction, typename Sample, typename Mask_>
auto sampled_relative(const BSDFPtr_ &bsdf, const Context &ctx, const Interaction &si, const Sample &bs,
                      const Mask_ &active) {
    auto value = bsdf->eval(ctx, si, bs.wo, active);
    Mask_ null = active && has_flag(bs.sampled_type, BSDFFlags::Null);
    if (dr::any_or<true>(null))
        value = dr::select(null, bsdf->eval_null_transmission(si, active), value);
    return relative(value);
}

/// a's value with b's derivative (dr::replace_grad; a itself in variants without gradients).
template <typename Value> Value with_grad(const Value &a, const Value &b) {
    if constexpr (dr::is_diff_v<Value>)
        return dr::replace_grad(a, b);
    else
        return (void) b, a;
}

/// A derivative pass's BSDF sample (`bs`, its weight, and `pdf`, the BSDF's pdf towards the
/// emitter sample), as path replay weighs it: the sample detached, the BSDF's value (or, past
/// a null lobe, its null transmission: sampled_relative) differentiated at the detached
/// direction, the weight's value unchanged (Mueller matrices: value / detached pdf). Where
/// the direction carries gradients (moves with a roughness) differentiating it would
/// differentiate the sample's motion, not the integrand (measured: d/dalpha of the wrong
/// sign, for roughconductor as for fluo_qd; as Mitsuba's path). Where it does not, the
/// weight value/pdf differentiated as sampled counts the lobe choice's probability (a
/// mask's opacity came out 0.00074 against 0.00177 by differences; now 0.00191): smooth and
/// null lobes take the value's derivative, delta lobes keep theirs (a smooth conductor's
/// Fresnel factor; their value at the direction is 0). Nothing in a render (`derivative`
/// false: render_forward/backward set it) whose direction carries no gradient (primal
/// kernels are unchanged).
template <typename BSDFPtr_, typename Context, typename Interaction, typename Sample, typename Float_,
          typename Weight, typename Mask_>
void detach_moving_sample(const BSDFPtr_ &bsdf, const Context &ctx, const Interaction &si, Sample &bs, Float_ &pdf,
                          Weight &weight, const Mask_ &active, bool derivative) {
    if constexpr (dr::is_diff_v<Float_>) {
        bool moving = dr::grad_enabled(bs.wo);
        if (!moving && !derivative)
            return;
        if (moving) {
            bs = dr::detach(bs);
            pdf = dr::detach(pdf);
        }
        if constexpr (is_polarized_v<Weight>) {
            if (moving) {
                auto [value, p] = bsdf->eval_pdf(ctx, si, bs.wo, active);
                weight = dr::select(p > 0.f, value / dr::detach(p), dr::detach(weight));
            }
        } else {
            Weight replayed = dr::detach(weight) * sampled_relative(bsdf, ctx, si, dr::detach(bs), active);
            Mask_ delta = has_flag(bs.sampled_type, BSDFFlags::DeltaReflection) ||
                          has_flag(bs.sampled_type, BSDFFlags::DeltaTransmission);
            weight = moving ? replayed : dr::select(delta, weight, replayed);
        }
    } else {
        (void) bsdf, (void) ctx, (void) si, (void) bs, (void) pdf, (void) weight, (void) active, (void) derivative;
    }
}

/// A single-lane JIT (or scalar) value read on the host.
template <typename Float> double host_value(const Float &v) { return (double) dr::slice(dr::detach(v), 0); }

/// Where gradients flow into a material's re-emission strength (c·Q, Q), its shift weight
/// in the elastic/shift choice is at least this (relative to the strength 1): a strength
/// of 0 would never draw the shift, and its derivative would be lost (any positive weight
/// keeps the estimate unbiased; primal renders without gradients are unchanged).
constexpr float GradientShiftFloor = 0.05f;

/// The elastic/shift choice at a fluorescent vertex, per hero wavelength (the estimator of
/// every material's jit_choose): with elastic weight `we` and shift weight `wf` ≥ 0 (any
/// positive value where the shift integrand is, so the estimate stays unbiased), the shift
/// is taken with probability 1 − pe, pe = we/(we + wf), decided by u1.
template <typename Value> struct ShiftChoice {
    using VMask = dr::mask_t<Value>;
    VMask valid, shifted;
    Value pe;

    template <typename ActiveMask>
    ShiftChoice(const Value &we, const Value &wf, const Value &u1, const ActiveMask &active) {
        Value total = we + wf;
        valid = VMask(active) && total > 0.f && dr::isfinite(total);
        pe = dr::select(valid, we / total, 1.f);
        shifted = valid && u1 >= pe && wf > 0.f;
    }

    /// 1/probability of the event taken, given the sampled shift's density `pdf` (0 where
    /// nothing valid was taken); lanes whose pdf is 0 or not finite leave `shifted`.
    Value weight(const Value &pdf, const Value &u1) {
        Value scale = dr::select(shifted, dr::rcp((1.f - pe) * pdf), dr::rcp(pe));
        shifted &= pdf > 0.f && dr::isfinite(pdf);
        return dr::select(valid && dr::isfinite(scale) && (shifted || u1 < pe), scale, 0.f);
    }
};

/// Armed when a fluorescent material is constructed (a scene is being loaded), disarmed by
/// the first warning: one "needs fluo_path" warning per loaded scene.
inline std::atomic<bool> &unmanaged_warning_armed() {
    static std::atomic<bool> armed{ true };
    return armed;
}

/// What fluo_path and fluo_volpath need of a fluorescent BSDF, per lane, in every variant.
template <typename Float, typename Spectrum> class BispectralBSDF {
public:
    MI_IMPORT_TYPES()
    using WMask = dr::mask_t<UnpolarizedSpectrum>;
    BispectralBSDF() { unmanaged_warning_armed().store(true, std::memory_order_relaxed); }
    virtual ~BispectralBSDF() = default;

    /// fluo_path/fluo_volpath mark the materials they transport (wrapped ones included)
    /// when they prepare a render. A fluorescent material sampled by any other integrator
    /// (Mitsuba's path, volpath, direct, ...) renders its elastic part only, and says so
    /// once per loaded scene (warn_if_unmanaged, called from sample(); in the llvm/cuda
    /// variants at trace time).
    void set_managed(bool managed) const { m_managed.store(managed, std::memory_order_relaxed); }

    void warn_if_unmanaged(const char *plugin) const {
        // (the armed flag first: jit_fluorescent may ask Rust, not per vertex once warned)
        if (m_managed.load(std::memory_order_relaxed) || !unmanaged_warning_armed().load(std::memory_order_relaxed) ||
            !jit_fluorescent())
            return;
        if (unmanaged_warning_armed().exchange(false, std::memory_order_relaxed)) {
            constexpr const char *ClassName = "fluo";
            Log(Warn, "%s: this material fluoresces, but the scene's integrator does not transport "
                      "fluorescence: only its elastic (non-shifted) part is rendered (in RGB variants an "
                      "equal-energy approximation). Use <integrator type=\"fluo_path\"/> to render "
                      "fluorescence. (This warning is printed once per scene.)", plugin);
        }
    }

    /// Host: whether the material re-emits at all (e.g. c > 0 and Q > 0).
    virtual bool jit_fluorescent() const = 0;
    /// Host: the emission range (nm) it re-emits into.
    virtual fluo::Range jit_emission_range() const = 0;
    /// Host: the excitation range (nm) it absorbs to re-emit from; a material that varies
    /// over the surface gives everything (each vertex intersects its own band).
    virtual fluo::Range jit_excitation_range() const { return { 0.0, 1e30 }; }

    /// RGB reduced transport: the vertex operator is Σ_t w_t·M_t with f = M/π, the K×K
    /// matrices M_t reduced once per render for `transport` (host, row major, sized K·K
    /// by the caller) and the weights w_t per lane (differentiable). Returns whether the
    /// operator includes the elastic part (otherwise fluo_path adds jit_elastic_albedo as
    /// per-band albedos).
    static constexpr size_t MaxTerms = 3;
    virtual bool jit_reduced_matrices(const fluo::TransportBasis &transport,
                                      std::array<std::vector<double>, MaxTerms> &m) const = 0;
    virtual std::array<Float, MaxTerms> jit_reduced_weights() const = 0;

    /// RGB reduced transport with gradients on parameters baked into the matrices (fluo_jung's
    /// λe and s, fluo_gmm's mixture, fluo_qd's radius and density): matrices D_d (host, row
    /// major, K·K each, or n_nodes·K·K at the cosine nodes of a direction-dependent lobe,
    /// jit_reduced_nodes; appended to `d` by the callee), D_d = ∂A/∂θ_d at this render's values, which the vertex operator
    /// adds with the weights jit_reduced_derivative_weights() (per lane, one per D_d, in the
    /// same order), each (θ_d − detach(θ_d)) times the lane's weight of the term D_d
    /// differentiates: zero in value, so A is unchanged and its derivative along θ_d is that
    /// weight times D_d. Returns how many (0: none, the default; asked when a render starts,
    /// so only materials whose such parameters carry gradients pay for it).
    virtual size_t jit_reduced_derivatives(const fluo::TransportBasis & /* transport */,
                                           std::vector<std::vector<double>> & /* d */) const {
        return 0;
    }
    virtual std::vector<Float> jit_reduced_derivative_weights(const SurfaceInteraction3f & /* si */,
                                                              Mask /* active */) const {
        return {};
    }

    /// Elastic albedo at si.wavelengths (spectral), or its linear sRGB (RGB variant).
    virtual UnpolarizedSpectrum jit_elastic_albedo(const SurfaceInteraction3f &si, Mask active) const = 0;

    /// Spectral: per hero wavelength λo = si.wavelengths, choose the elastic event or a
    /// shift to λi ∈ [range_lo, range_hi] (the lights' range), with uniform numbers u1
    /// (choice), u2 (λi). Returns the wavelengths to continue with, the estimator's
    /// weight (1/probability; detached), which wavelengths shifted, and for those the
    /// reradiation π·f_fl(λi, λo) (differentiable), and the model a varying material picked
    /// at this vertex (`local`, handed back to jit_reradiation; 0 for the others). A
    /// Lambertian lobe (f_fl·cos θo = that value·cos θo/π) needs no further call. Last, where
    /// the material's own (elastic) lobe is Lambertian (jit_lambertian_elastic), its albedo at
    /// λo as the choice read it (differentiable), which SurfaceShift evaluates that lobe with
    /// (the BSDF is then not called: its albedo is not read twice per vertex); else −1.
    using Choice =
        std::tuple<Wavelength, UnpolarizedSpectrum, WMask, UnpolarizedSpectrum, UInt32, UnpolarizedSpectrum>;
    /// The choice that keeps every wavelength (RGB variants, where fluo_path does not call
    /// jit_choose, and materials that do not re-emit).
    static Choice elastic_only(const Wavelength &lambda_o) {
        return { lambda_o, UnpolarizedSpectrum(1.f), WMask(false), UnpolarizedSpectrum(0.f), UInt32(0),
                 UnpolarizedSpectrum(-1.f) };
    }
    /// Host: whether jit_choose may hand back the elastic lobe's albedo (Choice's last entry).
    virtual bool jit_lambertian_elastic() const { return false; }
    virtual Choice jit_choose(const SurfaceInteraction3f &si, const Wavelength &u1, const Wavelength &u2,
                              double range_lo, double range_hi, Mask active) const = 0;

    /// Many materials (JIT variants): a material whose choice and reradiation lobe read data
    /// of its own alone (no texture, no gradient) is joinable; one member of its class joins
    /// the data of every joinable member (jit_join, `members`: the class's, this one among
    /// them; null: none joined) and then evaluates the lanes of all of them from it, with
    /// `member` the lane's index in `members` (read per lane by the BSDF's registry id). One
    /// evaluation per class instead of a callable traced per material: the spectral choice
    /// and lobe (FluorescentSet), the RGB transport's direction-dependent lobe (jit_lobe_joined).
    using Joined = std::shared_ptr<const void>;
    virtual bool jit_joinable() const { return false; }
    /// Members of one class join only with those of an equal tag: what differs between
    /// materials but enters the joined evaluation as a constant of the kernel (fluo_qd: its
    /// microfacet distribution).
    virtual std::string jit_join_tag() const { return {}; }
    virtual Joined jit_join(const std::vector<const BispectralBSDF *> & /* members */) const { return nullptr; }
    virtual Choice jit_choose_joined(const Joined & /* joined */, const UInt32 & /* member */,
                                     const SurfaceInteraction3f &si, const Wavelength & /* u1 */,
                                     const Wavelength & /* u2 */, double /* range_lo */, double /* range_hi */,
                                     Mask /* active */) const {
        return elastic_only(si.wavelengths);
    }
    /// Joined members' own BSDF (their elastic lobe) read per lane from the joined data: where
    /// a class says so (jit_elastic_joined), fluo_path and fluo_volpath evaluate its members'
    /// eval_pdf_sample here and the call over the scene's BSDFs traces nothing for them (a
    /// coating's callable was most of 200 coatings' first render). Its tag then holds what the
    /// lobe reads of the first member alone (fluo_qd: distribution and substrate).
    using EvalPdfSample = std::tuple<Spectrum, Float, BSDFSample3f, Spectrum>;
    static EvalPdfSample no_eval_pdf_sample() {
        return { dr::zeros<Spectrum>(), dr::zeros<Float>(), dr::zeros<BSDFSample3f>(), dr::zeros<Spectrum>() };
    }
    virtual bool jit_elastic_joined() const { return false; }
    virtual EvalPdfSample jit_eval_pdf_sample_joined(const Joined & /* joined */, const UInt32 & /* member */,
                                                     const BSDFContext & /* ctx */,
                                                     const SurfaceInteraction3f & /* si */,
                                                     const Vector3f & /* wo */, const Float & /* sample1 */,
                                                     const Point2f & /* sample2 */, Mask /* active */) const {
        return no_eval_pdf_sample();
    }
    /// RGB reduced transport of joined members with a direction-dependent lobe: jit_lobe of
    /// member `member` (its roughness; the terms' matrices and node weights the transport
    /// gathers itself, by the same member index).
    virtual std::pair<Float, Float> jit_lobe_joined(const Joined & /* joined */, const UInt32 & /* member */,
                                                    const SurfaceInteraction3f &si, const Vector3f &wo,
                                                    Mask active) const {
        return jit_lobe(si, wo, active);
    }
    /// jit_reradiation of joined members (`local`: jit_choose_joined's); Lambertian by default.
    virtual std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum>
    jit_reradiation_joined(const Joined & /* joined */, const SurfaceInteraction3f &si,
                           const UnpolarizedSpectrum &rerad, const UInt32 & /* local */, const Vector3f &wo_a,
                           const Vector3f &wo_b, Mask /* active */) const {
        return { rerad * lambert(si, wo_a), rerad * lambert(si, wo_b) };
    }

    /// RGB reduced transport of a material whose reradiation varies over the surface among
    /// a finite set of Lambertian operators (fluo_jung's textured parameters: one per dye
    /// shape): the K×K matrices M_n (host, row major, f = M_n/π; into `m`, sized by the
    /// callee), of which a lane's vertex adds w·M_n with (n, w) from jit_reduced_select.
    /// Returns how many (0: none, the default).
    virtual size_t jit_reduced_table(const fluo::TransportBasis & /* transport */,
                                     std::vector<double> & /* m */) const {
        return 0;
    }
    virtual std::pair<UInt32, Float> jit_reduced_select(const SurfaceInteraction3f & /* si */,
                                                        Mask /* active */) const {
        return { UInt32(0), Float(0.f) };
    }
    /// Derivatives of jit_reduced_table's operators along d parameters that vary per hit (a
    /// textured dye shape's λe and s): d more tables of its layout, [d][n][K][K], asked when
    /// a render begins (0: none, the default); a lane adds Σ_d w_d·D_{d,n} with the weights
    /// of jit_reduced_select_derivatives (one per table, zero in value: θ − detach(θ) times
    /// the hit's w), n being jit_reduced_select's.
    virtual size_t jit_reduced_table_derivatives(const fluo::TransportBasis & /* transport */,
                                                 std::vector<double> & /* d */) const {
        return 0;
    }
    virtual std::vector<Float> jit_reduced_select_derivatives(const SurfaceInteraction3f & /* si */,
                                                              Mask /* active */) const {
        return {};
    }

    // A reradiation lobe that depends on the directions (fluo_qd's microfacet lobe)
    // overrides the three methods below; fluo_path then calls them per vertex (and only
    // in scenes holding such a material: the Lambertian ones keep the calls above).

    /// Host: whether the reradiation lobe is Lambertian (f_fl·cos θo = rerad·cos θo/π).
    virtual bool jit_lambertian() const { return true; }
    /// Host: whether jit_reduced_weights and jit_elastic_albedo are the same at every hit
    /// (no texture): the reduced transport may then form the operator once per render.
    virtual bool jit_uniform() const { return false; }

    /// cos θo/π where both directions are above the surface, else 0.
    static Float lambert(const SurfaceInteraction3f &si, const Vector3f &wo) {
        return dr::select(Frame3f::cos_theta(si.wi) > 0.f && Frame3f::cos_theta(wo) > 0.f,
                          Frame3f::cos_theta(wo) * dr::InvPi<Float>, 0.f);
    }

    /// Spectral: f_fl·cos θo towards wo_a and wo_b, given jit_choose's `rerad` and `local`
    /// for the shifted wavelengths, with si.wavelengths = λi.
    virtual std::pair<UnpolarizedSpectrum, UnpolarizedSpectrum>
    jit_reradiation(const SurfaceInteraction3f &si, const UnpolarizedSpectrum &rerad, const UInt32 & /* local */,
                    const Vector3f &wo_a, const Vector3f &wo_b, Mask /* active */) const {
        return { rerad * lambert(si, wo_a), rerad * lambert(si, wo_b) };
    }

    /// RGB: a direction-dependent reradiation operator lobe(ωi, ωo)·w_0·M(cos θ) (cos θ = ωi·h
    /// and the lobe from jit_lobe, w_0 from jit_reduced_weights) written as
    /// M(cos θ) = Σ_t s_t(cos θ)·B_t, s_t linear between n nodes at cos θ = j/(n − 1): the
    /// K×K matrices B_t into `m` (host, row major, sized K·K by the caller; as
    /// jit_reduced_matrices) and s into `nodes` ([n][MaxTerms], sized by the callee). Returns
    /// n; 0 for a Lambertian material (jit_reduced_matrices serves it). The elastic part is
    /// the BSDF's own value, reduced as a native BSDF's.
    virtual size_t jit_reduced_nodes(const fluo::TransportBasis & /* transport */,
                                     std::array<std::vector<double>, MaxTerms> & /* m */,
                                     std::vector<double> & /* nodes */) const {
        return 0;
    }
    /// The lobe factor and cos θ of a direction-dependent operator for direction wo.
    virtual std::pair<Float, Float> jit_lobe(const SurfaceInteraction3f &si, const Vector3f &wo,
                                             Mask /* active */) const {
        return { lambert(si, wo), Float(0.f) };
    }

    /// A direction-dependent operator that varies over the surface among a finite set of
    /// models (fluo_qd's textured parameters: coatings baked on levels): every model's
    /// jit_reduced_nodes terms, B_t into `m` ([model][MaxTerms][K][K], sized by the callee)
    /// and their weights at the n cosine nodes into `nodes` ([model][n][MaxTerms]), n into
    /// `n_nodes`. Returns how many models (0: none, the default). Per lane the vertex's
    /// operator is then estimated as lobe·w·M_m(cos θ) for the (model m, weight w) that
    /// jit_reduced_pick draws with the uniform number u (a model of the hit's mixture picked
    /// with its probability: unbiased for the mixture, as jit_choose's pick in the spectral
    /// variants), the lobe from jit_lobe.
    virtual size_t jit_reduced_nodes_table(const fluo::TransportBasis & /* transport */,
                                           std::vector<double> & /* m */, std::vector<double> & /* nodes */,
                                           size_t & /* n_nodes */) const {
        return 0;
    }
    virtual std::pair<UInt32, Float> jit_reduced_pick(const SurfaceInteraction3f & /* si */, const Float & /* u */,
                                                      Mask /* active */) const {
        return { UInt32(0), Float(0.f) };
    }

private:
    mutable std::atomic<bool> m_managed{ false };
};

/// Per wavelength, `light` leaving unpolarized where `mask` holds, else `value`: in the
/// polarized variants a depolarizer (Mueller matrix with only its (0, 0) entry) replaces
/// those wavelengths' entries, as reradiated light carries no polarization; elsewhere a
/// plain select.
template <typename Spectrum, typename WMask, typename Unpolarized>
Spectrum select_unpolarized(const WMask &mask, const Unpolarized &light, const Spectrum &value) {
    if constexpr (is_polarized_v<Spectrum>) {
        Spectrum d = depolarizer<Spectrum>(Spectrum(light)), out = value;
        for (size_t i = 0; i < 4; ++i)
            for (size_t j = 0; j < 4; ++j)
                out(i, j) = dr::select(mask, d(i, j), value(i, j));
        return out;
    } else {
        return dr::select(mask, light, value);
    }
}

/// The hero wavelengths' uniform numbers from the first: u[j] = frac(u[0] + j/N), each
/// uniform on its own (SurfaceShift::choose draws them so). A material that spends u[0] on
/// a pick and rescales it calls this again, so every wavelength's number stays uniform given
/// the pick.
template <typename Wavelength> void rotate_hero(Wavelength &u) {
    constexpr size_t N = dr::size_v<Wavelength>;
    for (size_t j = 1; j < N; ++j) {
        auto v = u[0] + (float) j / (float) N;
        u[j] = dr::select(v >= 1.f, v - 1.f, v);
    }
}

/// Per lane, a where `m` holds, else b (tuples of Dr.Jit values).
template <typename M, typename... Ts>
std::tuple<Ts...> select_tuple(const M &m, const std::tuple<Ts...> &a, const std::tuple<Ts...> &b) {
    return std::apply(
        [&](const auto &...x) {
            return std::apply([&](const auto &...y) { return std::tuple<Ts...>(Ts(dr::select(m, x, y))...); }, b);
        },
        a);
}

/// The fluorescent BSDFs (or media) a render transports, looked up per vertex by address
/// (sorted; a dynamic_cast there compares type names across libraries: ~3 % of a scalar
/// vertex): Base is Mitsuba's interface (BSDF, Medium), Iface fluo's.
template <typename Base, typename Iface> class InterfaceSet {
public:
    template <typename B> void assign(const std::vector<B *> &objects) {
        m_entries.clear();
        for (B *b : objects)
            m_entries.emplace_back(dynamic_cast<const Base *>(b), b);
        std::sort(m_entries.begin(), m_entries.end());
    }
    /// fluo's interface of `b` when the render transports it, else nullptr.
    const Iface *find(const Base *b) const {
        auto it = std::lower_bound(m_entries.begin(), m_entries.end(), std::make_pair(b, (const Iface *) nullptr));
        return it != m_entries.end() && it->first == b ? it->second : nullptr;
    }
    void clear() { m_entries.clear(); }
    size_t size() const { return m_entries.size(); }
    bool empty() const { return m_entries.empty(); }

private:
    std::vector<std::pair<const Base *, const Iface *>> m_entries;
};

/// With more fluorescent materials than this, a JIT render reads the per-material data that
/// can be read per lane from tables (FluorescentSet's joined classes, the reduced transport's
/// operators) rather than tracing a call per material; with fewer, literals keep their kernels
/// small.
inline constexpr size_t ManyMaterials = 8;

/// Joinable materials (Bispectral::jit_joinable; `ids`: their BSDFs' registry ids, `keys`: a
/// caller's further key each) grouped by class, tag and key, each group joined by its first
/// member (jit_join; groups it refuses are left out): per group the indices of its members,
/// the joined data and the registry id → 1 + member index table.
template <typename Bispectral> struct JoinedGroup {
    std::vector<size_t> members;
    typename Bispectral::Joined joined;
    std::vector<uint32_t> slots;
};
template <typename Bispectral>
std::vector<JoinedGroup<Bispectral>> join_classes(const std::vector<const Bispectral *> &materials,
                                                  const std::vector<uint32_t> &ids,
                                                  const std::vector<std::string> &keys) {
    std::vector<std::pair<std::string, std::vector<size_t>>> classes;
    for (size_t i = 0; i < materials.size(); ++i) {
        std::string name =
            std::string(typeid(*materials[i]).name()) + "/" + materials[i]->jit_join_tag() + "/" + keys[i];
        auto it = std::find_if(classes.begin(), classes.end(), [&](const auto &c) { return c.first == name; });
        if (it == classes.end())
            it = classes.insert(classes.end(), { name, {} });
        it->second.push_back(i);
    }
    std::vector<JoinedGroup<Bispectral>> groups;
    for (auto &[name, members] : classes) {
        std::vector<const Bispectral *> ms;
        uint32_t top = 0;
        for (size_t i : members) {
            ms.push_back(materials[i]);
            top = std::max(top, ids[i]);
        }
        typename Bispectral::Joined joined = ms.front()->jit_join(ms);
        if (!joined)
            continue;
        std::vector<uint32_t> slots(top + 1, 0u);
        for (size_t m = 0; m < members.size(); ++m)
            slots[ids[members[m]]] = (uint32_t) m + 1u;
        groups.push_back({ std::move(members), std::move(joined), std::move(slots) });
    }
    return groups;
}

/// The fluorescent BSDFs of a render; in the JIT variants with many of them (more than
/// ManyMaterials), the joinable ones (Bispectral::jit_join) grouped by class (RGB: those
/// classes whose own BSDF is evaluated joined, the rest of RGB's per-material data being the
/// reduced transport's): SurfaceShift reads a lane's member index by the BSDF's registry id
/// and calls one material per class, where a dispatch would trace a callable per material
/// (200 distinct dyes or coatings: most of their first render).
template <typename Float, typename Spectrum>
class FluorescentSet : public InterfaceSet<BSDF<Float, Spectrum>, BispectralBSDF<Float, Spectrum>> {
public:
    using Bispectral = BispectralBSDF<Float, Spectrum>;
    using UInt32 = dr::uint32_array_t<Float>;
    struct Group {
        const Bispectral *first; ///< evaluates the class's lanes
        typename Bispectral::Joined joined;
        DynamicBuffer<UInt32> slots; ///< registry id → 1 + member index (0: not in the group)
        uint32_t n_slots;
        bool elastic; ///< the members' own BSDF too (Bispectral::jit_elastic_joined)
    };

    template <typename B> void assign(const std::vector<B *> &objects) {
        InterfaceSet<BSDF<Float, Spectrum>, Bispectral>::assign(objects);
        m_groups.clear();
        m_joined.clear();
        m_elastic.clear();
        if constexpr (dr::is_jit_v<Float>) {
            if (objects.size() > ManyMaterials)
                join(objects);
        }
        // (joined members' choices read their class's tables and give no albedo)
        m_lambertian = std::any_of(objects.begin(), objects.end(), [this](const B *b) {
            return b->jit_lambertian_elastic() && !joined(dynamic_cast<const BSDF<Float, Spectrum> *>(b));
        });
    }
    /// JIT, many materials: the joinable ones grouped by class (join_classes).
    template <typename B> void join(const std::vector<B *> &objects) {
        std::vector<const Bispectral *> materials;
        std::vector<const BSDF<Float, Spectrum> *> bases;
        std::vector<uint32_t> ids;
        for (B *b : objects) {
            const auto *base = dynamic_cast<const BSDF<Float, Spectrum> *>(b);
            uint32_t id = base ? jit_registry_id(base) : 0u;
            if (id == 0 || !b->jit_joinable() || (!is_spectral_v<Spectrum> && !b->jit_elastic_joined()))
                continue;
            materials.push_back(b);
            bases.push_back(base);
            ids.push_back(id);
        }
        for (auto &g : join_classes(materials, ids, std::vector<std::string>(materials.size()))) {
            const Bispectral *first = materials[g.members.front()];
            bool elastic = first->jit_elastic_joined();
            m_groups.push_back(Group{ first, std::move(g.joined),
                                      dr::load<DynamicBuffer<UInt32>>(g.slots.data(), g.slots.size()),
                                      (uint32_t) g.slots.size(), elastic });
            for (size_t i : g.members) {
                m_joined.push_back(bases[i]);
                if (elastic)
                    m_elastic.push_back(bases[i]);
            }
        }
        std::sort(m_joined.begin(), m_joined.end());
        std::sort(m_elastic.begin(), m_elastic.end());
    }
    const std::vector<Group> &groups() const { return m_groups; }
    /// Whether `b`'s lanes are evaluated through its group.
    bool joined(const BSDF<Float, Spectrum> *b) const {
        return std::binary_search(m_joined.begin(), m_joined.end(), b);
    }
    /// Whether `b`'s own BSDF is evaluated through its group (any such member: `b` null).
    bool elastic_joined(const BSDF<Float, Spectrum> *b = nullptr) const {
        return b ? std::binary_search(m_elastic.begin(), m_elastic.end(), b) : !m_elastic.empty();
    }
    /// Whether some material of the set is reached through a call.
    bool dispatched() const { return m_joined.size() < this->size(); }
    /// Whether some material's choice may hand back its Lambertian albedo (jit_lambertian_elastic).
    bool lambertian() const { return m_lambertian; }

private:
    bool m_lambertian = false;
    std::vector<Group> m_groups;
    std::vector<const BSDF<Float, Spectrum> *> m_joined, m_elastic;
};

/// A fluorescent surface vertex of the spectral integrators (fluo_path,
/// fluo_volpath): per lane and hero wavelength the elastic event or a shift (the material's
/// jit_choose), then the shifted wavelengths' reradiation lobe in place of the BSDF's value
/// and weight. The estimator is fluo_path.cpp's (its docs).
template <typename Float, typename Spectrum> struct SurfaceShift {
    MI_IMPORT_TYPES(BSDF, BSDFPtr, Sampler)
    using Bispectral = BispectralBSDF<Float, Spectrum>;
    using WMask = dr::mask_t<UnpolarizedSpectrum>;

    UnpolarizedSpectrum scale = 1.f, rerad = 0.f;
    UnpolarizedSpectrum elastic = -1.f; ///< the choice's Lambertian albedo (−1: none)
    WMask shifted = false;
    bool chose = false; ///< whether choose() ran
    UInt32 local = 0;  ///< the model a varying material picked (jit_choose)
    UInt32 group = 0;  ///< 1 + the lane's group in FluorescentSet (0: none)
    UInt32 member = 0; ///< the lane's index in its group
    bool located = false;

    /// Each lane's group and member index, by its BSDF's registry id (JIT variants; every
    /// lane's, whatever the mask of the call that first asks: eval_pdf_sample may be asked
    /// for lanes choose() was not).
    void locate(const FluorescentSet<Float, Spectrum> &set, const BSDFPtr &bsdf) {
        located = true;
        if constexpr (dr::is_jit_v<Float>) {
            if (set.groups().empty())
                return;
            UInt32 id = dr::reinterpret_array<UInt32>(bsdf);
            for (uint32_t gi = 0; gi < (uint32_t) set.groups().size(); ++gi) {
                const auto &g = set.groups()[gi];
                Mask known = id < g.n_slots;
                UInt32 slot = fluo_detail::fetch<UInt32>(g.slots, id, known);
                Mask in = known && slot > 0u;
                group = dr::select(in, gi + 1u, group);
                member = dr::select(in, slot - 1u, member);
            }
        } else {
            (void) set, (void) bsdf;
        }
    }

    /// The BSDF's eval_pdf_sample at the vertex: a Lambertian lobe with the albedo the
    /// choice handed back (Choice's last entry) here, the lanes of members evaluated joined
    /// (FluorescentSet::elastic_joined) from their group, the others through the call, in
    /// which those members trace nothing.
    typename Bispectral::EvalPdfSample eval_pdf_sample(const FluorescentSet<Float, Spectrum> &set,
                                                       const BSDFPtr &bsdf, const BSDFContext &ctx,
                                                       const SurfaceInteraction3f &si, const Vector3f &wo,
                                                       const Float &sample1, const Point2f &sample2,
                                                       const Mask &active) {
        if (!chose || !set.lambertian())
            return evaluate(set, bsdf, ctx, si, wo, sample1, sample2, active);
        Mask lambert = active && elastic[0] >= 0.f;
        if (dr::none_or<false>(lambert))
            return evaluate(set, bsdf, ctx, si, wo, sample1, sample2, active);
        auto albedo = [this] { return elastic; };
        auto [val, pdf] = Lambertian<Float, Spectrum>::eval_pdf(ctx, si, wo, lambert, albedo);
        auto [bs, weight] = Lambertian<Float, Spectrum>::sample(ctx, si, sample2, lambert, albedo);
        typename Bispectral::EvalPdfSample own(val, pdf, bs, weight);
        if (dr::all_or<false>(lambert))
            return own;
        return select_tuple(lambert, own, evaluate(set, bsdf, ctx, si, wo, sample1, sample2, active && !lambert));
    }

    /// eval_pdf_sample's lanes that call the BSDF or its joined group.
    typename Bispectral::EvalPdfSample evaluate(const FluorescentSet<Float, Spectrum> &set, const BSDFPtr &bsdf,
                                               const BSDFContext &ctx, const SurfaceInteraction3f &si,
                                               const Vector3f &wo, const Float &sample1, const Point2f &sample2,
                                               const Mask &active) {
        if (!set.elastic_joined())
            return bsdf->eval_pdf_sample(ctx, si, wo, sample1, sample2, active);
        if (!located)
            locate(set, bsdf);
        using Result = typename Bispectral::EvalPdfSample;
        Result out = Bispectral::no_eval_pdf_sample();
        Mask rest = active;
        for (uint32_t gi = 0; gi < (uint32_t) set.groups().size(); ++gi) {
            const auto &g = set.groups()[gi];
            if (!g.elastic)
                continue;
            Mask in = active && group == gi + 1u;
            out = select_tuple(
                in, g.first->jit_eval_pdf_sample_joined(g.joined, member, ctx, si, wo, sample1, sample2, in), out);
            rest &= !in;
        }
        Result r = dispatch_any(
            bsdf,
            [&set, &ctx](const BSDF *b, const SurfaceInteraction3f &si_, const Vector3f &wo_, const Float &s1,
                         const Point2f &s2, const Mask &on) -> Result {
                return set.elastic_joined(b) ? Bispectral::no_eval_pdf_sample()
                                             : b->eval_pdf_sample(ctx, si_, wo_, s1, s2, on);
            },
            si, wo, sample1, sample2, rest);
        return select_tuple(rest, r, out);
    }

    /// Choose per hero wavelength for the materials in `set`; si.wavelengths become the
    /// wavelengths to continue with (λi where shifted). [lo, hi]: the lights' range. One 2D
    /// number from `sampler` serves the four hero wavelengths, rotated by j/4 for the j-th
    /// (each uniform on its own, as Mitsuba's hero wavelengths are: every wavelength's
    /// estimate stays unbiased).
    void choose(const FluorescentSet<Float, Spectrum> &set, const BSDFPtr &bsdf, SurfaceInteraction3f &si,
                Sampler *sampler, const Mask &active, double lo, double hi) {
        Wavelength u1, u2;
        Point2f u = sampler->next_2d(active);
        u1[0] = u.x();
        u2[0] = u.y();
        rotate_hero(u1);
        rotate_hero(u2);
        typename Bispectral::Choice c = Bispectral::elastic_only(si.wavelengths);
        Mask rest = active;
        locate(set, bsdf);
        for (uint32_t gi = 0; gi < (uint32_t) set.groups().size(); ++gi) {
            const auto &g = set.groups()[gi];
            Mask in = active && group == gi + 1u;
            c = select_tuple(in, g.first->jit_choose_joined(g.joined, member, si, u1, u2, lo, hi, in), c);
            rest &= !in;
        }
        if (set.dispatched())
            c = select_tuple(rest, dispatch_any(
                bsdf,
                [lo, hi, &set](const BSDF *b, const SurfaceInteraction3f &si_, const Wavelength &u1_,
                               const Wavelength &u2_, const Mask &on) {
                    const Bispectral *f = set.find(b);
                    return f && !set.joined(b) ? f->jit_choose(si_, u1_, u2_, lo, hi, on)
                                               : Bispectral::elastic_only(si_.wavelengths);
                },
                si, u1, u2, rest), c);
        auto [li, sc, sh, rr, lc, el] = c;
        Mask has_bsdf = active && bsdf != nullptr;
        chose = true;
        elastic = dr::select(has_bsdf, el, -1.f);
        si.wavelengths = dr::select(has_bsdf, li, si.wavelengths);
        scale = dr::select(has_bsdf, sc, 1.f);
        shifted = WMask(has_bsdf) && sh;
        rerad = dr::select(shifted, rr, 0.f);
        local = dr::select(has_bsdf, lc, 0u);
    }

    /// The vertex's f·cos towards the emitter sample `wo` (`val`, the BSDF's value on entry)
    /// and its weight for the sampled direction `bs` (`weight`, the BSDF's on entry): the
    /// shifted wavelengths' reradiation lobe, Lambertian unless the scene holds a
    /// direction-dependent one (`directional`: asked per direction), times the choice's weight.
    void apply(const FluorescentSet<Float, Spectrum> &set, const BSDFPtr &bsdf, const SurfaceInteraction3f &si,
               bool directional, const Vector3f &wo, const BSDFSample3f &bs, const Mask &active, Spectrum &val,
               Spectrum &weight) const {
        UnpolarizedSpectrum v_em, v_bs;
        if (directional) {
            Mask rest = active && dr::any(shifted);
            v_em = v_bs = 0.f;
            for (uint32_t gi = 0; gi < (uint32_t) set.groups().size(); ++gi) {
                const auto &g = set.groups()[gi];
                Mask in = rest && group == gi + 1u;
                auto [a, b] = g.first->jit_reradiation_joined(g.joined, si, rerad, local, wo, bs.wo, in);
                v_em = dr::select(in, a, v_em);
                v_bs = dr::select(in, b, v_bs);
                rest &= !in;
            }
            if (set.dispatched()) {
                auto [a, b] = dispatch_any(
                    bsdf,
                    [&set](const BSDF *b_, const SurfaceInteraction3f &si_, const UnpolarizedSpectrum &rr_,
                           const UInt32 &lc_, const Vector3f &wa, const Vector3f &wb, const Mask &on) {
                        const Bispectral *f = set.find(b_);
                        if (f && !set.joined(b_))
                            return f->jit_reradiation(si_, rr_, lc_, wa, wb, on);
                        return std::make_pair(UnpolarizedSpectrum(0.f), UnpolarizedSpectrum(0.f));
                    },
                    si, rerad, local, wo, bs.wo, rest);
                v_em = dr::select(rest, a, v_em);
                v_bs = dr::select(rest, b, v_bs);
            }
        } else {
            v_em = rerad * Bispectral::lambert(si, wo);
            v_bs = rerad * Bispectral::lambert(si, bs.wo);
        }
        val = select_unpolarized(shifted, v_em, val) * scale;
        UnpolarizedSpectrum w_bs = dr::select(bs.pdf > 0.f, v_bs / bs.pdf, 0.f);
        weight = select_unpolarized(shifted, w_bs, weight) * scale;
    }
};

NAMESPACE_END(fluo_detail)
NAMESPACE_END(mitsuba)
