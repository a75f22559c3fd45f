// fluo's plugins in Mitsuba's vectorised (JIT) variants: llvm_ad_rgb, llvm_ad_spectral and
// the same code on the CUDA backend, cuda_ad_rgb and cuda_ad_spectral.
//
// Dr.Jit cannot trace calls into Rust, so in these variants Rust runs at load time and in
// parameters_changed() only: it validates the parameters and bakes tables (absorption CDFs,
// reduced matrices, RGB parts), which the shims evaluate per lane with Dr.Jit types. The
// scalar variants keep calling Rust per sample and are the reference the JIT shims are tested
// against (tests/python/test_llvm.py: same images within noise, same values at random points).
//
// This header holds what every JIT shim shares: the registration for the llvm variants, the
// interface fluo_path reaches fluorescent BSDFs through (dr::dispatch), and the closed forms
// of Jung's dye (differentiable in its parameters).
#pragma once

#include <mitsuba/core/distr_1d.h>
#include <mitsuba/core/plugin.h>
#include <mitsuba/render/bsdf.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <tuple>
#include <vector>

#include "fluo_common.h"

NAMESPACE_BEGIN(mitsuba)
NAMESPACE_BEGIN(fluo_detail)

/// Register plugin class template T for the vectorised variants: llvm_ad_rgb,
/// llvm_ad_spectral, cuda_ad_rgb and cuda_ad_spectral (the same code on Dr.Jit's CUDA
/// backend: it compiles without a GPU and runs where one is present). The name must be one
/// of jit_plugin() in fluo_common.h, which keeps the "not available" stub off them.
template <template <typename, typename> class T> void register_jit_plugin(const char *name, ObjectType type) {
    if (!served_variant(name, "llvm_ad_rgb"))
        Throw("fluo: plugin \"%s\" is registered for the JIT variants but not listed in jit_plugin()", name);
    using LFloat = dr::DiffArray<JitBackend::LLVM, float>;
    using CFloat = dr::DiffArray<JitBackend::CUDA, float>;
    PluginManager *pm = PluginManager::instance();
    pm->register_plugin(
        name, "llvm_ad_rgb", type,
        [](void *, const Properties &p) -> ref<Object> { return new T<LFloat, Color<LFloat, 3>>(p); }, nullptr,
        nullptr);
    pm->register_plugin(
        name, "llvm_ad_spectral", type,
        [](void *, const Properties &p) -> ref<Object> { return new T<LFloat, Spectrum<LFloat, 4>>(p); },
        nullptr, nullptr);
    pm->register_plugin(
        name, "cuda_ad_rgb", type,
        [](void *, const Properties &p) -> ref<Object> { return new T<CFloat, Color<CFloat, 3>>(p); }, nullptr,
        nullptr);
    pm->register_plugin(
        name, "cuda_ad_spectral", type,
        [](void *, const Properties &p) -> ref<Object> { return new T<CFloat, Spectrum<CFloat, 4>>(p); },
        nullptr, nullptr);
}

/// dr::dispatch exists for JIT pointer arrays only; a scalar pointer is called directly.
template <typename Ptr, typename Func, typename... Args>
auto dispatch_any(const Ptr &self, const Func &func, const Args &...args) {
    if constexpr (dr::is_jit_v<Ptr>)
        return dr::dispatch(self, func, args...);
    else
        return func(self, args...);
}

/// A single-lane JIT (or scalar) value read on the host.
template <typename Float> double host_value(const Float &v) {
    if constexpr (dr::is_jit_v<Float>)
        return (double) dr::slice(dr::detach(v), 0);
    else
        return (double) v;
}

/// Jung et al.'s dye in closed form (core/src/models/jung.rs has the equations and their
/// reading; test_llvm.py holds these against the Rust model at random wavelengths):
/// α = λe·s/(2λe − s), e(λ) = b(3(λ − λe)/α)·9/(8α), a(λ) = b(v − 3) with
/// v = 3(2 − kλ)/(αk(kλ − 1)), k = 2/(λe − α), on the support ((λe−α)(λe+α)/(λe+3α), λe − α).
/// Written with Dr.Jit types so that gradients reach λe and s.
template <typename Value> struct JungDye {
    Value peak, alpha, edge, k, lo;

    template <typename Param> JungDye(const Param &emission_peak, const Param &stokes_shift) {
        peak = Value(emission_peak);
        Value s = Value(stokes_shift);
        alpha = peak * s / (2.f * peak - s);
        edge = peak - alpha;
        k = 2.f / edge;
        lo = edge * (peak + alpha) / (peak + 3.f * alpha);
    }

    /// Quadratic b-spline of eq. 3: support (−3, 3), b(0) = 1.
    static Value bspline(const Value &x) {
        Value ax = dr::abs(x), d = 3.f - ax;
        return dr::select(ax <= 1.f, 1.f - x * x * (1.f / 3.f), dr::select(ax < 3.f, d * d * (1.f / 6.f), 0.f));
    }

    /// e(λ), nm⁻¹, unit integral (eq. 5).
    Value emission(const Value &lambda) const {
        return bspline(3.f * (lambda - peak) / alpha) * (9.f / 8.f) / alpha;
    }

    /// The absorption's b-spline coordinate v(λ) = 3(2 − kλ)/(αk(kλ − 1)) ∈ (0, 6) on the
    /// support (decreasing in λ), its inverse λ(v) = (2 + q)/(k(1 + q)) with q = vαk/3, and
    /// |dv/dλ| = 3/(α(kλ − 1)²): excitation wavelengths are sampled in v from a fixed table
    /// of b(v − 3) and mapped to λ, with the exact Jacobian in the pdf.
    Value v_of(const Value &lambda) const {
        Value kl = k * lambda;
        return 3.f * (2.f - kl) / (alpha * k * (kl - 1.f));
    }
    Value lambda_of(const Value &v) const {
        Value q = v * alpha * k * (1.f / 3.f);
        return (2.f + q) / (k * (1.f + q));
    }
    Value dv_dlambda(const Value &lambda) const {
        Value d = k * lambda - 1.f;
        return 3.f / (alpha * d * d);
    }

    /// a(λ) ∈ [0, 1], peak 1 at λe − s (eq. 6, mirrored over wavenumber).
    Value absorption(const Value &lambda) const {
        dr::mask_t<Value> inside = lambda > lo && lambda < edge;
        return dr::select(inside, bspline(dr::select(inside, v_of(lambda), 0.f) - 3.f), 0.f);
    }
};

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

/// Inverse CDF within a cell of width h where a density is linear from f0 to f1: the offset
/// whose integral from the cell's start is delta (clamped to the cell's mass), the
/// quadratic's root in the cancellation-free form 2δ/(f0 + √(f0² + 2(f1 − f0)δ/h)) (as
/// matrix.rs and the QD model's row sampling).
template <typename Value> Value linear_cell_inverse(const Value &f0, const Value &f1, const Value &h, const Value &delta) {
    Value d = dr::clip(delta, 0.f, .5f * h * (f0 + f1));
    Value disc = dr::maximum(dr::fmadd(f0, f0, 2.f * (f1 - f0) / h * d), 0.f);
    Value denom = f0 + dr::sqrt(disc);
    return dr::select(denom > 0.f, 2.f * d / denom, 0.f);
}

/// A piecewise-linear function's nodes on the device with a bucket index (one bucket per
/// `step` nm, never wider than a cell: a node's cell is its bucket's or the next), else
/// binary search.
template <typename Float> struct JitGrid {
    using UInt32 = dr::uint32_array_t<Float>;
    using Mask = dr::mask_t<Float>;
    static constexpr size_t MaxBuckets = 1 << 16;
    /// λ in cell k (x0 ≤ λ ≤ x1, clamped to the grid) at fraction f.
    struct Cell {
        UInt32 k;
        Float f, x0, x1;
    };

    std::vector<double> host;
    Float nodes;
    UInt32 buckets;
    float step = 1.f, l0 = 0.f, l1 = 1.f;
    uint32_t n = 2, n_buckets = 0;
    bool bucketed = false;

    void set(const std::vector<double> &x) {
        host = x;
        n = (uint32_t) x.size();
        std::vector<float> f(x.begin(), x.end());
        nodes = dr::load<Float>(f.data(), f.size());
        l0 = (float) x.front();
        l1 = (float) x.back();
        double narrowest = x.back() - x.front();
        for (size_t k = 0; k + 1 < x.size(); ++k)
            narrowest = std::min(narrowest, x[k + 1] - x[k]);
        double s = narrowest * (1.0 - 1e-6); // float rounding must not span two cells
        size_t count = s > 0.0 ? (size_t) std::ceil((x.back() - x.front()) / s) + 1 : 0;
        bucketed = count >= 1 && count <= MaxBuckets;
        if (!bucketed)
            return;
        std::vector<uint32_t> b(count);
        for (size_t i = 0, k = 0; i < count; ++i) {
            double at = x.front() + (double) i * s;
            while (k + 2 < x.size() && x[k + 1] <= at)
                ++k;
            b[i] = (uint32_t) k;
        }
        buckets = dr::load<UInt32>(b.data(), b.size());
        step = (float) s;
        n_buckets = (uint32_t) count;
    }

    Cell cell(const Float &lambda, const Mask &active) const {
        Float x = dr::clip(lambda, l0, l1);
        UInt32 k;
        if (bucketed) {
            UInt32 b = UInt32(dr::minimum(dr::floor((x - l0) * (1.f / step)), (float) (n_buckets - 1)));
            k = dr::gather<UInt32>(buckets, b, active);
            k = dr::select(k + 2 < n && dr::gather<Float>(nodes, k + 1, active) <= x, k + 1, k);
        } else {
            k = dr::binary_search<UInt32>(1, n - 1, [&](const UInt32 &i) {
                    return dr::gather<Float>(nodes, i, active) <= x;
                }) - 1;
        }
        Float x0 = dr::gather<Float>(nodes, k, active), x1 = dr::gather<Float>(nodes, k + 1, active);
        return { k, dr::clip((x - x0) / (x1 - x0), 0.f, 1.f), x0, x1 };
    }

    /// The cell index of λ known on the host, and its fraction.
    std::pair<size_t, double> host_cell(double lambda) const {
        double x = std::clamp(lambda, host.front(), host.back());
        size_t k = (size_t) (std::upper_bound(host.begin(), host.end(), x) - host.begin());
        k = std::clamp(k, (size_t) 1, host.size() - 1) - 1;
        return { k, std::clamp((x - host[k]) / (host[k + 1] - host[k]), 0.0, 1.0) };
    }
};

/// Several piecewise-linear functions' nodes (one grid per measured file, per baked coating
/// model), concatenated on the device: per grid its offset, size, ends and step (> 0 where it
/// is uniform, as BFC files and most CSV ones are: a cell is then one multiplication), else
/// (`bucketed` grids: the coatings' piecewise-uniform ones) a bucket index as JitGrid's, else
/// a binary search per lane over the longest grid; a lane reads the grid it selects. Each
/// grid is strictly increasing with at least 2 nodes (checked by Rust).
template <typename Float> struct JitGridSet {
    using UInt32 = dr::uint32_array_t<Float>;
    using Mask = dr::mask_t<Float>;
    using FloatStorage = DynamicBuffer<Float>;
    using UInt32Storage = DynamicBuffer<UInt32>;

    std::vector<float> host;
    std::vector<uint32_t> off, n, b_off, b_n;
    std::vector<float> lo, hi, step, b_step;
    std::vector<uint32_t> host_buckets;
    FloatStorage nodes;
    FloatStorage d_ends;  ///< per grid: lo, hi, step, bucket step (several grids)
    UInt32Storage d_size; ///< per grid: offset, size, bucket offset, bucket count (several grids)
    UInt32Storage buckets;
    uint32_t n_max = 2;
    bool any_uniform = false, all_uniform = true, bucketed = true;

    /// Append a grid (host); upload() once all are in. `bucketed`: index its cells (every
    /// grid of a set alike).
    template <typename Nodes> void add(const Nodes &v, bool with_buckets = false) {
        off.push_back((uint32_t) host.size());
        n.push_back((uint32_t) v.size());
        n_max = std::max(n_max, (uint32_t) v.size());
        double h = (v.back() - v.front()) / (double) (v.size() - 1);
        bool uniform = true;
        for (size_t i = 0; i < v.size(); ++i)
            uniform &= std::abs(v[i] - (v.front() + (double) i * h)) <= 1e-6 * h;
        any_uniform |= uniform;
        all_uniform &= uniform;
        lo.push_back((float) v.front());
        hi.push_back((float) v.back());
        step.push_back(uniform ? (float) h : 0.f);
        host.insert(host.end(), v.begin(), v.end());
        // the bucket index (JitGrid::set): one bucket per narrowest cell
        double narrowest = v.back() - v.front();
        for (size_t k = 0; k + 1 < v.size(); ++k)
            narrowest = std::min(narrowest, (double) (v[k + 1] - v[k]));
        double bs = narrowest * (1.0 - 1e-6);
        size_t count = bs > 0.0 ? (size_t) std::ceil((v.back() - v.front()) / bs) + 1 : 0;
        bucketed &= with_buckets && count >= 1 && count <= JitGrid<Float>::MaxBuckets;
        b_off.push_back((uint32_t) host_buckets.size());
        b_n.push_back((uint32_t) count);
        b_step.push_back((float) bs);
        if (!with_buckets || count > JitGrid<Float>::MaxBuckets)
            return;
        for (size_t i = 0, k = 0; i < count; ++i) {
            double at = v.front() + (double) i * bs;
            while (k + 2 < v.size() && v[k + 1] <= at)
                ++k;
            host_buckets.push_back((uint32_t) k);
        }
    }
    void upload() {
        nodes = dr::load<FloatStorage>(host.data(), host.size());
        if (bucketed)
            buckets = dr::load<UInt32Storage>(host_buckets.data(), host_buckets.size());
        if (off.size() > 1) {
            std::vector<uint32_t> size;
            std::vector<float> ends;
            for (size_t i = 0; i < off.size(); ++i) {
                size.insert(size.end(), { off[i], n[i], b_off[i], b_n[i] });
                ends.insert(ends.end(), { lo[i], hi[i], step[i], b_step[i] });
            }
            d_size = dr::load<UInt32Storage>(size.data(), size.size());
            d_ends = dr::load<FloatStorage>(ends.data(), ends.size());
        }
    }

    /// A lane's grid `which` (literals when there is one).
    struct At {
        UInt32 off, n, b_off, b_n;
        Float lo, hi, step, b_step;
    };
    At at(const UInt32 &which, const Mask &active) const {
        if (off.size() == 1)
            return { UInt32(off[0]), UInt32(n[0]), UInt32(b_off[0]), UInt32(b_n[0]),
                     Float(lo[0]),   Float(hi[0]), Float(step[0]),   Float(b_step[0]) };
        UInt32 i = which * 4;
        return { dr::gather<UInt32>(d_size, i, active),     dr::gather<UInt32>(d_size, i + 1, active),
                 dr::gather<UInt32>(d_size, i + 2, active), dr::gather<UInt32>(d_size, i + 3, active),
                 dr::gather<Float>(d_ends, i, active),      dr::gather<Float>(d_ends, i + 1, active),
                 dr::gather<Float>(d_ends, i + 2, active),  dr::gather<Float>(d_ends, i + 3, active) };
    }

    /// The cell j ∈ [0, n − 2] (within the lane's grid) holding x ∈ [lo, hi] (the last
    /// node ≤ x), and its ends.
    std::tuple<UInt32, Float, Float> cell(const At &g, const Float &x, const Mask &active) const {
        UInt32 j(0);
        if (!all_uniform && bucketed) {
            UInt32 b = UInt32(dr::clip(dr::floor((x - g.lo) / g.b_step), 0.f, Float(g.b_n - 1)));
            j = dr::gather<UInt32>(buckets, g.b_off + b, active);
            j = dr::select(j + 2 < g.n && dr::gather<Float>(nodes, g.off + j + 1, active) <= x, j + 1, j);
        } else if (!all_uniform) {
            // over the longest grid, each lane's nodes clamped to its own last one
            UInt32 last = g.n - 1;
            j = dr::binary_search<UInt32>(1, n_max - 1, [&](const UInt32 &i) {
                    return dr::gather<Float>(nodes, g.off + dr::minimum(i, last), active) <= x;
                }) - 1;
            j = dr::minimum(j, g.n - 2);
        }
        Float x0(0.f), x1(0.f);
        if (!all_uniform) {
            x0 = dr::gather<Float>(nodes, g.off + j, active);
            x1 = dr::gather<Float>(nodes, g.off + j + 1, active);
        }
        if (any_uniform) {
            Mask uniform = g.step > 0.f;
            Float s = dr::select(uniform, g.step, 1.f);
            UInt32 ju = UInt32(dr::clip(dr::floor((x - g.lo) / s), 0.f, Float(g.n - 2)));
            Float u0 = dr::fmadd(Float(ju), s, g.lo);
            j = dr::select(uniform, ju, j);
            x0 = dr::select(uniform, u0, x0);
            x1 = dr::select(uniform, u0 + s, x1);
        }
        return { j, x0, x1 };
    }
};

/// The hull of the emission ranges of several models (a material that varies over the
/// surface; nullptr: a model that does not re-emit, left out); {0, 0} if none re-emits.
inline fluo::Range emission_hull(const std::vector<const fluo::Fluorescence *> &models) {
    fluo::Range r{ 0.0, 0.0 };
    bool any = false;
    for (const fluo::Fluorescence *m : models) {
        if (!m)
            continue;
        fluo::Range e = fluo::fluo_emission_range(*m);
        r = any ? fluo::Range{ std::min(r.lo, e.lo), std::max(r.hi, e.hi) } : e;
        any = true;
    }
    return r;
}

/// Per lane, the bracketing levels of x among `levels` (host, sorted, at most a few dozen:
/// compared as constants): (i, t) with x = (1 − t)·levels[i] + t·levels[i + 1], t = 0 at or
/// below the first level (and for x NaN), 1 at or above the last (i = n − 2), as the scalar
/// shims' bracket; one level: (0, 0).
template <typename Float> std::pair<dr::uint32_array_t<Float>, Float> lane_bracket(const std::vector<float> &levels,
                                                                                  const Float &x) {
    using UInt32 = dr::uint32_array_t<Float>;
    size_t n = levels.size();
    if (n < 2)
        return { UInt32(0), Float(0.f) };
    UInt32 i(0);
    Float l0(levels[0]), l1(levels[1]);
    for (size_t k = 1; k + 1 < n; ++k) {
        dr::mask_t<Float> above = x >= levels[k];
        i = dr::select(above, (uint32_t) k, i);
        l0 = dr::select(above, levels[k], l0);
        l1 = dr::select(above, levels[k + 1], l1);
    }
    Float t = (x - l0) / (l1 - l0);
    return { i, dr::select(dr::isnan(t), 0.f, dr::clip(t, 0.f, 1.f)) };
}

/// Per lane, the index of the level nearest x (ties: the lower; NaN: the first), as
/// nearest_level (fluo_param_texture.h).
template <typename Float> dr::uint32_array_t<Float> lane_nearest(const std::vector<float> &levels, const Float &x) {
    using UInt32 = dr::uint32_array_t<Float>;
    UInt32 i(0);
    for (size_t k = 1; k < levels.size(); ++k)
        i = dr::select(x - levels[k - 1] > levels[k] - x, (uint32_t) k, i);
    return i;
}

/// Jakob & Hanika's sigmoid of a polynomial in λ (nm): S(x) = 1/2 + x / (2√(1 + x²))
/// (core/src/sigmoid.rs). x is clamped to ±1e18 first, where S is 0 or 1 in single
/// precision already: x² of a larger x overflows a float (coefficients such as
/// (0, 0, 1e20) gave 0.5 instead of 1).
template <typename Value, typename Coeff>
Value sigmoid_polynomial(const Value &lambda, const Coeff &c0, const Coeff &c1, const Coeff &c2) {
    Value x = dr::fmadd(dr::fmadd(Value(c0), lambda, Value(c1)), lambda, Value(c2));
    x = dr::clip(x, -1e18f, 1e18f);
    return .5f + .5f * x * dr::rsqrt(dr::fmadd(x, x, 1.f));
}

/// What fluo_path needs of a fluorescent BSDF in the JIT variants, per lane.
template <typename Float, typename Spectrum> class JitBispectral {
public:
    MI_IMPORT_TYPES()
    using WMask = dr::mask_t<UnpolarizedSpectrum>;
    virtual ~JitBispectral() = default;

    /// Host: whether the material re-emits at all (e.g. c > 0 and Q > 0).
    virtual bool jit_fluorescent() const = 0;
    /// Host: the emission range (nm) it re-emits into.
    virtual fluo::Range jit_emission_range() const = 0;

    /// RGB reduced transport: the vertex operator is Σ_t w_t·M_t with f = M/π, the K×K
    /// matrices M_t reduced once per render for `transport` (host, row major, sized K·K
    /// by the caller) and the weights w_t per lane (differentiable). Returns whether the
    /// operator includes the elastic part (otherwise fluo_path adds jit_elastic_albedo as
    /// per-band albedos).
    static constexpr size_t MaxTerms = 3;
    virtual bool jit_reduced_matrices(const fluo::TransportBasis &transport,
                                      std::array<std::vector<double>, MaxTerms> &m) const = 0;
    virtual std::array<Float, MaxTerms> jit_reduced_weights() const = 0;

    /// Elastic albedo at si.wavelengths (spectral), or its linear sRGB (RGB variant).
    virtual UnpolarizedSpectrum jit_elastic_albedo(const SurfaceInteraction3f &si, Mask active) const = 0;

    /// Spectral: per hero wavelength λo = si.wavelengths, choose the elastic event or a
    /// shift to λi ∈ [range_lo, range_hi] (the lights' range), with uniform numbers u1
    /// (choice), u2 (λi). Returns the wavelengths to continue with, the estimator's
    /// weight (1/probability; detached), which wavelengths shifted, and for those the
    /// reradiation π·f_fl(λi, λo) (differentiable), and the model a varying material picked
    /// at this vertex (`local`, handed back to jit_reradiation; 0 for the others). A
    /// Lambertian lobe (f_fl·cos θo = that value·cos θo/π) needs no further call.
    using Choice = std::tuple<Wavelength, UnpolarizedSpectrum, WMask, UnpolarizedSpectrum, UInt32>;
    /// The choice that keeps every wavelength (RGB variants, where fluo_path does not call
    /// jit_choose, and materials that do not re-emit).
    static Choice elastic_only(const Wavelength &lambda_o) {
        return { lambda_o, UnpolarizedSpectrum(1.f), WMask(false), UnpolarizedSpectrum(0.f), UInt32(0) };
    }
    virtual Choice jit_choose(const SurfaceInteraction3f &si, const Wavelength &u1, const Wavelength &u2,
                              double range_lo, double range_hi, Mask active) const = 0;

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

    // A reradiation lobe that depends on the directions (fluo_qd's microfacet lobe)
    // overrides the three methods below; fluo_path then calls them per vertex (and only
    // in scenes holding such a material: the Lambertian ones keep the calls above).

    /// Host: whether the reradiation lobe is Lambertian (f_fl·cos θo = rerad·cos θo/π).
    virtual bool jit_lambertian() const { return true; }

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
};

/// A fluorescent surface vertex of the vectorised spectral integrators (fluo_path,
/// fluo_volpath): per lane and hero wavelength the elastic event or a shift (the material's
/// jit_choose), then the shifted wavelengths' reradiation lobe in place of the BSDF's value
/// and weight. The estimator is fluo_path.cpp's (its docs).
template <typename Float, typename Spectrum> struct JitSurfaceShift {
    MI_IMPORT_TYPES(BSDF, BSDFPtr, Sampler)
    using Bispectral = JitBispectral<Float, Spectrum>;
    using WMask = dr::mask_t<UnpolarizedSpectrum>;

    UnpolarizedSpectrum scale = 1.f, rerad = 0.f;
    WMask shifted = false;
    UInt32 local = 0; ///< the model a varying material picked (jit_choose)

    /// Choose per hero wavelength (four 2D numbers from `sampler`); si.wavelengths become
    /// the wavelengths to continue with (λi where shifted). [lo, hi]: the lights' range.
    void choose(const BSDFPtr &bsdf, SurfaceInteraction3f &si, Sampler *sampler, const Mask &active, double lo,
                double hi) {
        Wavelength u1, u2;
        for (size_t j = 0; j < dr::size_v<Wavelength>; ++j) {
            Point2f u = sampler->next_2d(active);
            u1[j] = u.x();
            u2[j] = u.y();
        }
        auto [li, sc, sh, rr, lc] = dispatch_any(
            bsdf,
            [lo, hi](const BSDF *b, const SurfaceInteraction3f &si_, const Wavelength &u1_, const Wavelength &u2_,
                     const Mask &on) {
                if (auto *f = dynamic_cast<const Bispectral *>(b); f && f->jit_fluorescent())
                    return f->jit_choose(si_, u1_, u2_, lo, hi, on);
                return Bispectral::elastic_only(si_.wavelengths);
            },
            si, u1, u2, active);
        Mask has_bsdf = active && bsdf != nullptr;
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
    void apply(const BSDFPtr &bsdf, const SurfaceInteraction3f &si, bool directional, const Vector3f &wo,
               const BSDFSample3f &bs, const Mask &active, UnpolarizedSpectrum &val,
               UnpolarizedSpectrum &weight) const {
        UnpolarizedSpectrum v_em, v_bs;
        if (directional) {
            std::tie(v_em, v_bs) = dispatch_any(
                bsdf,
                [](const BSDF *b, const SurfaceInteraction3f &si_, const UnpolarizedSpectrum &rr_, const UInt32 &lc_,
                   const Vector3f &wa, const Vector3f &wb, const Mask &on) {
                    if (auto *f = dynamic_cast<const Bispectral *>(b); f && f->jit_fluorescent())
                        return f->jit_reradiation(si_, rr_, lc_, wa, wb, on);
                    return std::make_pair(UnpolarizedSpectrum(0.f), UnpolarizedSpectrum(0.f));
                },
                si, rerad, local, wo, bs.wo, active && dr::any(shifted));
        } else {
            v_em = rerad * Bispectral::lambert(si, wo);
            v_bs = rerad * Bispectral::lambert(si, bs.wo);
        }
        val = dr::select(shifted, v_em, val) * scale;
        UnpolarizedSpectrum w_bs = dr::select(bs.pdf > 0.f, v_bs / bs.pdf, 0.f);
        weight = dr::select(shifted, w_bs, weight) * scale;
    }
};

NAMESPACE_END(fluo_detail)
NAMESPACE_END(mitsuba)
