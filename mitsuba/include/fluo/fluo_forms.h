// The closed forms and table lookups the plugins evaluate per lane, one C++ home each:
// Jung's dye, the sigmoid polynomial, piecewise-linear tables (LaneGrid, LaneGridSet) and
// their inverse CDF within a cell, and parameter levels. Written with Dr.Jit types: Float
// is a scalar in scalar_* variants and a JIT array in llvm_ad_* / cuda_ad_* ones.
#pragma once

#include <mitsuba/core/fwd.h>
#include <mitsuba/core/vector.h>

#include <algorithm>
#include <array>
#include <memory>
#include <cmath>
#include <tuple>
#include <utility>
#include <vector>

#include "fluo_common.h"

NAMESPACE_BEGIN(mitsuba)
NAMESPACE_BEGIN(fluo_detail)

/// Jung et al.'s dye in closed form (core/src/models/jung.rs has the equations and their
/// reading):
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

    /// B(v) = ∫_0^v b(t − 3) dt for v ∈ [0, 6] (8/3 in all): (v)³/18, then 4/3 + y − y³/9
    /// (y = v − 3 ∈ [−1, 1]), then 8/3 − (6 − v)³/18.
    static Value bspline_cdf(const Value &v) {
        Value y = dr::clip(v, 0.f, 6.f) - 3.f, l = 3.f + y, h = 3.f - y;
        return dr::select(y <= -1.f, l * l * l * (1.f / 18.f),
                          dr::select(y < 1.f, 4.f / 3.f + y - y * y * y * (1.f / 9.f),
                                     8.f / 3.f - h * h * h * (1.f / 18.f)));
    }
    /// The v with B(v) = t, t ∈ [0, 8/3]: cube roots on the outer pieces; on the middle one
    /// the root in [−1, 1] of y³ − 9y + 9t − 12 = 0 (three real roots: the trigonometric form).
    /// Sampling v ∝ b(v − 3) on [v_a, v_b] is B⁻¹(B(v_a) + u·(B(v_b) − B(v_a))).
    static Value bspline_cdf_inverse(const Value &t_) {
        Value t = dr::clip(t_, 0.f, 8.f / 3.f);
        Value lo = dr::cbrt(18.f * t) - 3.f, hi = 3.f - dr::cbrt(18.f * (8.f / 3.f - t));
        const float r3 = 1.7320508f; // √3
        Value c = dr::clip((12.f - 9.f * t) / (6.f * r3), -1.f, 1.f);
        Value mid = 2.f * r3 * dr::cos(dr::acos(c) * (1.f / 3.f) - 2.0943951f);
        return dr::clip(dr::select(t <= 4.f / 9.f, lo, dr::select(t < 20.f / 9.f, mid, hi)) + 3.f, 0.f, 6.f);
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

/// Per-vertex scratch of n values (one per mixture component, ...): inline up to N, on the
/// heap only beyond (the scalar variants run it per vertex, where a std::vector's
/// allocation cost ~7 % of a fluo_gmm vertex).
template <typename T, size_t N = 16> class Scratch {
public:
    explicit Scratch(size_t n = 0) { resize(n); }
    Scratch(Scratch &&o) noexcept { *this = std::move(o); }
    /// (moved, not copied: a fluo_gmm vertex's mixture, six scratches returned by value,
    /// spent ~4 % of a scalar vertex in copies)
    Scratch &operator=(Scratch &&o) noexcept {
        if (this != &o) {
            for (size_t i = 0; o.m_n <= N && i < o.m_n; ++i)
                m_local[i] = std::move(o.m_local[i]);
            m_heap = std::move(o.m_heap);
            m_n = o.m_n;
            m_cap = o.m_cap;
            o.m_n = o.m_cap = 0;
        }
        return *this;
    }
    void resize(size_t n) {
        if (n > N && n > m_cap) {
            m_heap.reset(new T[n]());
            m_cap = n;
        }
        m_n = n;
    }
    T &operator[](size_t i) { return m_n > N ? m_heap[i] : m_local[i]; }
    const T &operator[](size_t i) const { return m_n > N ? m_heap[i] : m_local[i]; }
    size_t size() const { return m_n; }

private:
    std::array<T, N> m_local{};
    std::unique_ptr<T[]> m_heap; // (not a std::vector: vector<bool> has no bool&)
    size_t m_n = 0, m_cap = 0;
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

/// A piecewise-linear function's nodes on the device. A grid of at most MaxSegments uniform
/// runs (fluo_qd's: Rust's lambda_grid) finds a cell by arithmetic, reading nothing; others
/// through a bucket index (one bucket per `step` nm, never wider than a cell: a node's cell
/// is its bucket's or the next), else by binary search.
template <typename Float> struct LaneGrid {
    using UInt32 = dr::uint32_array_t<Float>;
    static constexpr size_t MaxBuckets = 1 << 16;
    static constexpr size_t MaxSegments = 4;
    /// A uniform run: its first node, step and 1/step, its first cell's index and its last
    /// cell's offset from it (values of the kernel: dr::make_opaque).
    struct Segment {
        Float start, step, inv_step, last;
        UInt32 first;
    };
    /// λ in cell k (x0 ≤ λ ≤ x1, clamped to the grid) at fraction f; `Value`: a Float, or a
    /// packet of them (a lane's hero wavelengths).
    template <typename Value> struct CellOf {
        dr::uint32_array_t<Value> k;
        Value f, x0, x1;
        DRJIT_STRUCT(CellOf, k, f, x0, x1)
    };
    using Cell = CellOf<Float>;

    std::vector<double> host;
    DynamicBuffer<Float> nodes;
    DynamicBuffer<UInt32> buckets;
    float step = 1.f, l0 = 0.f, l1 = 1.f;
    uint32_t n = 2, n_buckets = 0;
    bool bucketed = false;
    std::vector<Segment> segments; ///< the grid's uniform runs, if at most MaxSegments
    /// The same as values of the kernel, not literals (JIT variants: instances whose grids
    /// differ share one callable; dr::make_opaque).
    Float v_l0 = 0.f, v_l1 = 1.f, v_inv_step = 1.f, v_last_bucket = 0.f;
    UInt32 v_n = 2;

    void set(const std::vector<double> &x) {
        host = x;
        n = (uint32_t) x.size();
        nodes = load_floats<DynamicBuffer<Float>>(x);
        l0 = (float) x.front();
        l1 = (float) x.back();
        segments.clear();
        for (size_t k = 0; k + 1 < x.size();) {
            double h = x[k + 1] - x[k];
            size_t e = k + 1;
            while (e + 1 < x.size() && std::abs((x[e + 1] - x[e]) - h) <= 1e-6 * h)
                ++e;
            double run = (x[e] - x[k]) / (double) (e - k);
            Segment sg{ Float((float) x[k]), Float((float) run), Float((float) (1.0 / run)),
                        Float((float) (e - k - 1)), UInt32((uint32_t) k) };
            dr::make_opaque(sg.start, sg.step, sg.inv_step, sg.last, sg.first);
            segments.push_back(sg);
            k = e;
        }
        if (segments.size() > MaxSegments)
            segments.clear();
        bucketed = false;
        n_buckets = 0;
        buckets = DynamicBuffer<UInt32>();
        if (!segments.empty()) { // (cells by arithmetic: no bucket index)
            opaque();
            return;
        }
        std::vector<uint32_t> b;
        auto [s, count] = bucket_index(x, true, b);
        bucketed = count >= 1 && count <= MaxBuckets;
        if (!bucketed) {
            opaque();
            return;
        }
        buckets = dr::load<DynamicBuffer<UInt32>>(b.data(), b.size());
        step = (float) s;
        n_buckets = (uint32_t) count;
        opaque();
    }

    /// The bucket index over nodes `x`: one bucket per narrowest cell, each the cell its start
    /// is in. Returns the buckets' step and count; appends them to `out` where `fill` and
    /// there are at most MaxBuckets.
    template <typename Nodes>
    static std::pair<double, size_t> bucket_index(const Nodes &x, bool fill, std::vector<uint32_t> &out) {
        double narrowest = x.back() - x.front();
        for (size_t k = 0; k + 1 < x.size(); ++k)
            narrowest = std::min(narrowest, (double) (x[k + 1] - x[k]));
        double s = narrowest * (1.0 - 1e-6); // float rounding must not span two cells
        size_t count = s > 0.0 ? (size_t) std::ceil((x.back() - x.front()) / s) + 1 : 0;
        for (size_t i = 0, k = 0; fill && count <= MaxBuckets && i < count; ++i) {
            double at = x.front() + (double) i * s;
            while (k + 2 < x.size() && x[k + 1] <= at)
                ++k;
            out.push_back((uint32_t) k);
        }
        return { s, count };
    }

    void opaque() {
        v_l0 = l0;
        v_l1 = l1;
        v_inv_step = 1.f / step;
        v_last_bucket = (float) (n_buckets > 0 ? n_buckets - 1 : 0);
        v_n = n;
        dr::make_opaque(v_l0, v_l1, v_inv_step, v_last_bucket, v_n);
    }

    template <typename Value> CellOf<Value> cell(const Value &lambda, const dr::mask_t<Value> &active) const {
        using UIntV = dr::uint32_array_t<Value>;
        Value x = dr::clip(lambda, v_l0, v_l1);
        if (!segments.empty()) {
            Value start(segments[0].start), step_(segments[0].step), inv(segments[0].inv_step),
                last(segments[0].last);
            UIntV first(segments[0].first);
            for (size_t i = 1; i < segments.size(); ++i) {
                const Segment &sg = segments[i];
                dr::mask_t<Value> in = x >= sg.start;
                start = dr::select(in, Value(sg.start), start);
                step_ = dr::select(in, Value(sg.step), step_);
                inv = dr::select(in, Value(sg.inv_step), inv);
                last = dr::select(in, Value(sg.last), last);
                first = dr::select(in, UIntV(sg.first), first);
            }
            Value j = dr::clip(dr::floor((x - start) * inv), 0.f, last);
            Value x0 = dr::fmadd(j, step_, start);
            return { first + UIntV(j), dr::clip((x - x0) * inv, 0.f, 1.f), x0, x0 + step_ };
        }
        UIntV k;
        if (bucketed) {
            UIntV b = UIntV(dr::minimum(dr::floor((x - v_l0) * v_inv_step), v_last_bucket));
            k = fluo_detail::fetch_each<UIntV>(buckets, b, active);
            k = dr::select(k + 2 < v_n && fluo_detail::fetch_each<Value>(nodes, k + 1, active) <= x, k + 1, k);
        } else {
            k = dr::binary_search<UIntV>(1, n - 1, [&](const UIntV &i) {
                    return fluo_detail::fetch_each<Value>(nodes, i, active) <= x;
                }) - 1;
        }
        Value x0 = fluo_detail::fetch_each<Value>(nodes, k, active),
              x1 = fluo_detail::fetch_each<Value>(nodes, k + 1, active);
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
/// (`bucketed` grids: the coatings' piecewise-uniform ones) a bucket index as LaneGrid's, else
/// a binary search per lane over the longest grid; a lane reads the grid it selects. Each
/// grid is strictly increasing with at least 2 nodes (checked by Rust).
template <typename Float> struct LaneGridSet {
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
        b_off.push_back((uint32_t) host_buckets.size());
        auto [bs, count] = LaneGrid<Float>::bucket_index(v, with_buckets, host_buckets);
        bucketed &= with_buckets && count >= 1 && count <= LaneGrid<Float>::MaxBuckets;
        b_n.push_back((uint32_t) count);
        b_step.push_back((float) bs);
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
        DRJIT_STRUCT(At, off, n, b_off, b_n, lo, hi, step, b_step)
    };
    At at(const UInt32 &which, const Mask &active) const {
        if (off.size() == 1)
            return { UInt32(off[0]), UInt32(n[0]), UInt32(b_off[0]), UInt32(b_n[0]),
                     Float(lo[0]),   Float(hi[0]), Float(step[0]),   Float(b_step[0]) };
        UInt32 i = which * 4;
        return { fluo_detail::fetch<UInt32>(d_size, i, active),     fluo_detail::fetch<UInt32>(d_size, i + 1, active),
                 fluo_detail::fetch<UInt32>(d_size, i + 2, active), fluo_detail::fetch<UInt32>(d_size, i + 3, active),
                 fluo_detail::fetch<Float>(d_ends, i, active),      fluo_detail::fetch<Float>(d_ends, i + 1, active),
                 fluo_detail::fetch<Float>(d_ends, i + 2, active),  fluo_detail::fetch<Float>(d_ends, i + 3, active) };
    }

    /// The cell j ∈ [0, n − 2] (within the lane's grid) holding x ∈ [lo, hi] (the last
    /// node ≤ x), and its ends. `Value`: a Float, or a packet of them (the four hero
    /// wavelengths of a lane, which share its grid).
    template <typename Value>
    std::tuple<dr::uint32_array_t<Value>, Value, Value> cell(const At &g, const Value &x,
                                                             const dr::mask_t<Value> &active) const {
        using UIntV = dr::uint32_array_t<Value>;
        UIntV j(0);
        if (!all_uniform && bucketed) {
            UIntV b = UIntV(dr::clip(dr::floor((x - g.lo) / g.b_step), 0.f, Value(Float(g.b_n - 1))));
            j = fluo_detail::fetch_each<UIntV>(buckets, b + g.b_off, active);
            j = dr::select(j + 2 < g.n && fluo_detail::fetch_each<Value>(nodes, g.off + j + 1, active) <= x, j + 1, j);
        } else if (!all_uniform) {
            // over the longest grid, each lane's nodes clamped to its own last one
            UIntV last(g.n - 1);
            j = dr::binary_search<UIntV>(1, n_max - 1, [&](const UIntV &i) {
                    return fluo_detail::fetch_each<Value>(nodes, g.off + dr::minimum(i, last), active) <= x;
                }) - 1;
            j = dr::minimum(j, g.n - 2);
        }
        Value x0(0.f), x1(0.f);
        if (!all_uniform) {
            x0 = fluo_detail::fetch_each<Value>(nodes, g.off + j, active);
            x1 = fluo_detail::fetch_each<Value>(nodes, g.off + j + 1, active);
        }
        if (any_uniform) {
            Mask uniform = g.step > 0.f;
            Float s = dr::select(uniform, g.step, 1.f);
            UIntV ju = UIntV(dr::clip(dr::floor((x - g.lo) / s), 0.f, Value(Float(g.n - 2))));
            Value u0 = dr::fmadd(Value(ju), s, g.lo);
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
/// below the first level (and for x NaN), 1 at or above the last (i = n − 2); one level:
/// (0, 0).
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

/// Per lane, the index of the level nearest x (levels sorted, non-empty; ties: the lower;
/// NaN: the first).
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

NAMESPACE_END(fluo_detail)
NAMESPACE_END(mitsuba)
