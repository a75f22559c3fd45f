// Shared helpers for the fluo Mitsuba plugins.
//
// The plugins parse Mitsuba Properties and hand the numbers to the Rust core through the
// cxx bridge (fluo-mitsuba/src/bridge.rs.h) at load and on parameter updates; Rust
// validates them and bakes what the plugins evaluate per lane at render time (Dr.Jit
// cannot trace calls into Rust, and no variant calls Rust per vertex).
#pragma once

#include <mitsuba/core/logger.h>
#include <mitsuba/core/plugin.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/core/spectrum.h>
#include <mitsuba/core/transform.h>
#include <mitsuba/render/texture.h>
#include <mitsuba/render/interaction.h>
#include <drjit/tensor.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <atomic>
#include <deque>
#include <functional>
#include <map>
#include <mutex>
#include <string>
#include <string_view>
#include <unordered_set>
#include <vector>

#include "fluo-mitsuba/src/bridge.rs.h"
#include "rust/cxx.h"

NAMESPACE_BEGIN(mitsuba)
NAMESPACE_BEGIN(fluo_detail)

/// dr::gather of one Float or UInt32 per lane from a buffer. The scalar variants read the
/// buffer in place: Dr.Jit's scalar gather is a call out of line (7.6 % of a scalar
/// fluo_qd render); an index out of range still goes through it (and its error).
template <typename T, typename Buffer, typename Index, typename Mask = bool>
DRJIT_INLINE T fetch(const Buffer &buffer, const Index &index, const Mask &active = true) {
    if constexpr (dr::is_array_v<T>) {
        return dr::gather<T>(buffer, index, active);
    } else {
        if (!active)
            return T(0);
        if (DRJIT_UNLIKELY((size_t) index >= buffer.size()))
            return dr::gather<T>(buffer, index, active);
        return buffer.data()[index];
    }
}

/// fetch for each hero wavelength: T a packet of Floats (a Wavelength), `index` and
/// `active` packets of its shape, one read per entry (in the scalar variants, the packet's
/// arithmetic around it stays in SIMD registers); T a Float: fetch itself.
template <typename T, typename Buffer, typename Index, typename Mask>
DRJIT_INLINE T fetch_each(const Buffer &buffer, const Index &index, const Mask &active) {
    if constexpr (dr::is_static_array_v<T>) {
        T out;
        for (size_t k = 0; k < dr::size_v<T>; ++k)
            out[k] = fetch<dr::value_t<T>>(buffer, index[k], active[k]);
        return out;
    } else {
        return fetch<T>(buffer, index, active);
    }
}

/// The first M of the N values of entry `index` of a buffer of packets (entry i is
/// buffer[N·i, N·i + N)), per hero wavelength where T is a Wavelength (as fetch_each): one
/// packet read per lane in the JIT variants (Dr.Jit's packet gather), M reads in place after
/// one range check in the scalar ones.
template <size_t N, size_t M, typename T, typename Buffer, typename Index, typename Mask>
DRJIT_INLINE std::array<T, M> fetch_packet(const Buffer &buffer, const Index &index, const Mask &active) {
    std::array<T, M> out;
    if constexpr (dr::is_static_array_v<T>) {
        for (size_t w = 0; w < dr::size_v<T>; ++w) {
            auto v = fetch_packet<N, M, dr::value_t<T>>(buffer, index[w], active[w]);
            for (size_t c = 0; c < M; ++c)
                out[c][w] = v[c];
        }
    } else if constexpr (dr::is_jit_v<T>) {
        auto v = dr::gather<dr::Array<T, N>>(buffer, index, active);
        for (size_t c = 0; c < M; ++c)
            out[c] = v[c];
    } else { // (one range check for the M)
        size_t at = N * (size_t) index;
        for (size_t c = 0; c < M; ++c)
            out[c] = active && at + M <= buffer.size() ? buffer.data()[at + c]
                                                       : fetch<T>(buffer, (uint32_t) (at + c), active);
    }
    return out;
}

/// Call into Rust; a Rust error (cxx's rust::Error) becomes a Mitsuba exception
/// that names the plugin and carries the Rust message.
template <typename F> auto rust_call(const char *plugin, F &&f) -> decltype(f()) {
    try {
        return f();
    } catch (const rust::Error &e) {
        Throw("%s: %s", plugin, e.what());
    }
}

/// Read a scalar property with a default, rejecting non-numeric input with a message that
/// names the parameter. T: float, or double where the values span beyond a float's range
/// (physical constants, media).
template <typename T = float>
inline double get_float(const char *plugin, const Properties &props, const char *name, double def) {
    if (!props.has_property(name))
        return def;
    try {
        return (double) props.get<T>(name);
    } catch (const std::exception &e) {
        Throw("%s: parameter \"%s\" must be a number (%s)", plugin, name, e.what());
    }
}

/// A string parameter, `def` when absent.
inline std::string get_string(const Properties &props, const char *name, const char *def) {
    return props.has_property(name) ? std::string(props.get<std::string_view>(name)) : def;
}

/// Counts the updates of fluo's plugins (UpdateRecord::update, accepted or refused: either
/// rebuilds): a render prepared before one (PreparedScene) prepares again.
inline std::atomic<uint64_t> &update_generation() {
    static std::atomic<uint64_t> generation{ 0 };
    return generation;
}

/// Run `obj`'s traverse() with `value(name, ptr, type)` per value and `child(name, object)`
/// per object, whose own traverse() follows where `child` returns true.
template <typename Value, typename Child> void visit(Object *obj, Value &&value, Child &&child) {
    struct Callback : TraversalCallback {
        Value &value;
        Child &child;
        Callback(Value &v, Child &c) : value(v), child(c) {}
        void put_value(std::string_view name, void *ptr, uint32_t, const std::type_info &type) override {
            value(name, ptr, type);
        }
        void put_object(std::string_view name, Object *o, uint32_t) override {
            if (child(name, o))
                o->traverse(this);
        }
    } callback(value, child);
    obj->traverse(&callback);
}

/// Every value mi.traverse shows of an object, its children's included (recursively), as
/// last accepted: a plugin's update is a transaction over them. `arm()` (from the plugin's
/// traverse(), before anyone can change a value) records them once; `update(self, commit)`
/// runs the plugin's validation and rebuild. If it throws, every recorded value is put back
/// (children first told through their own parameters_changed: a texture's or grid's derived
/// data follows), `commit` runs again on the restored values and the error propagates: a
/// refused update leaves the object and `mi.traverse` exactly as they were, and never blocks
/// a later unrelated one (a refused child value, such as fluo_qd's `eta`, is undone too).
/// After an accepted update the record is taken again.
template <typename Float> class UpdateRecord {
    using T = CoreAliases<Float>;
    using S = CoreAliases<dr::scalar_t<Float>>;
    struct Value {
        std::function<void()> restore;
    };
    std::vector<Value> m_values;
    std::vector<Object *> m_children; ///< deepest last
    bool m_armed = false;

    template <typename V> bool take(void *ptr, const std::type_info &type) {
        if (type != typeid(V))
            return false;
        V *p = static_cast<V *>(ptr);
        m_values.push_back({ [p, v = V(*p)] { *p = v; } });
        return true;
    }

    void record(Object *self) {
        m_values.clear();
        m_children.clear();
        std::unordered_set<Object *> seen{ self };
        auto value = [&](std::string_view, void *ptr, const std::type_info &type) {
            (void) (take<float>(ptr, type) || take<double>(ptr, type) || take<int>(ptr, type) ||
                    take<uint32_t>(ptr, type) || take<bool>(ptr, type) || take<Float>(ptr, type) ||
                    take<typename T::Color3f>(ptr, type) || take<typename S::Color3f>(ptr, type) ||
                    take<typename T::Vector3f>(ptr, type) || take<typename S::Vector3f>(ptr, type) ||
                    take<typename T::AffineTransform4f>(ptr, type) ||
                    take<typename S::AffineTransform4f>(ptr, type) ||
                    take<typename T::ProjectiveTransform4f>(ptr, type) ||
                    take<DynamicBuffer<Float>>(ptr, type) || take<typename T::TensorXf>(ptr, type) ||
                    take<typename T::TensorXf16>(ptr, type) || take<typename T::TensorXf64>(ptr, type));
        };
        visit(self, value, [&](std::string_view, Object *o) {
            if (!o || !seen.insert(o).second)
                return false;
            m_children.push_back(o); // (deepest last)
            return true;
        });
    }

public:
    void arm(Object *self) {
        if (m_armed)
            return;
        m_armed = true; // first: the traverse() below must not arm again
        record(self);
    }

    template <typename Commit> void update(Object *self, Commit &&commit) {
        int none = 0;
        update(self, none, commit);
    }

    /// The same, the plugin's own `state` (its configuration, in double precision) restored
    /// with the traversed values.
    template <typename State, typename Commit> void update(Object *self, State &state, Commit &&commit) {
        const State previous = state;
        update_generation().fetch_add(1, std::memory_order_acq_rel);
        try {
            commit();
        } catch (...) {
            state = previous;
            if (!m_armed)
                throw;
            for (auto &v : m_values)
                v.restore();
            for (auto it = m_children.rbegin(); it != m_children.rend(); ++it)
                (*it)->parameters_changed({});
            commit();
            throw;
        }
        if (m_armed)
            record(self);
    }
};

/// Numbers (doubles: Rust's tables) on the device as a float array.
template <typename Storage, typename Values> Storage load_floats(const Values &v) {
    std::vector<float> f(v.begin(), v.end());
    return dr::load<Storage>(f.data(), f.size());
}

/// A JIT array's n lanes on the host (detached). An array of one lane is broadcast: Dr.Jit
/// folds constant expressions (a texture or spectrum that does not vary, coefficients that
/// cancel) to a single lane, which a plain read-back of n would leave unfilled.
template <typename Float> std::vector<float> host_lanes(const Float &value, size_t n) {
    auto v = dr::detach(value);
    std::vector<float> out(n);
    if (dr::width(v) == 1) {
        std::fill(out.begin(), out.end(), (float) dr::slice(v));
        return out;
    }
    if (dr::width(v) != n)
        Throw("host_lanes: %zu lanes, %zu expected", dr::width(v), n);
    dr::eval(v);
    dr::store(out.data(), v);
    return out;
}

/// Many materials' tables in one array per Float type: Dr.Jit rounds every allocation up to
/// a power of two (a coating's 139 KB table took 256 KB of a process's memory), and a
/// class's joined evaluation (jit_join) reads its members' blocks where they are, with no
/// copy. A Block is one material's tables back to back; it keeps its place for its life
/// (freed space is reused first fit, the array grows by doubling from 1 GiB of untouched
/// host memory in llvm, and is released with the last block); lanes read it at an opaque
/// offset, so that instances share their code.
template <typename Float> class TableStore {
    using Storage = DynamicBuffer<Float>;
    using Index = DynamicBuffer<dr::uint32_array_t<Float>>;

public:
    class Block {
    public:
        Block() = default;
        Block(const Block &) = delete;
        Block &operator=(const Block &) = delete;
        ~Block() { release(); }
        /// Store `values` in place of the block's previous ones (placed before those are
        /// freed: an update of a store's only block does not empty and re-create the store,
        /// and a refused one leaves the block as it was).
        void assign(const std::vector<float> &values) {
            uint32_t at = values.empty() ? 0 : store().put(values);
            release();
            if (values.empty())
                return;
            m_at = at;
            m_size = (uint32_t) values.size();
            m_offset = dr::opaque<dr::uint32_array_t<Float>>(m_at);
        }
        uint32_t at() const { return m_at; }
        uint32_t size() const { return m_size; }
        /// Where the block starts in data(), as a lane reads it.
        const dr::uint32_array_t<Float> &offset() const { return m_offset; }
        const Storage &data() const { return store().m_data; }

    private:
        void release() {
            if (m_size)
                store().free(m_at, m_size);
            m_size = 0;
        }
        uint32_t m_at = 0, m_size = 0;
        dr::uint32_array_t<Float> m_offset = 0;
    };

private:
    static TableStore &store() {
        static TableStore *s = new TableStore(); // (emptied with its last block, never destroyed)
        return *s;
    }
    /// The used part of the array in a new one of `cap` entries.
    Storage copy(size_t cap) const {
        Storage out = dr::empty<Storage>(cap);
        if (m_end) {
            Index i = dr::arange<Index>(m_end);
            dr::scatter(out, dr::gather<Storage>(m_data, i), i);
        }
        dr::eval(out);
        return out;
    }
    uint32_t put(const std::vector<float> &values) {
        std::lock_guard<std::mutex> guard(m_mutex);
        if (values.size() > UINT32_MAX - (size_t) m_end)
            Throw("the tables of this scene's materials exceed 2^32 floats");
        uint32_t n = (uint32_t) values.size(), at = m_end;
        auto fit = std::find_if(m_free.begin(), m_free.end(), [&](const auto &f) { return f.second >= n; });
        if (fit != m_free.end()) {
            at = fit->first;
            if (fit->second > n)
                m_free[at + n] = fit->second - n;
            m_free.erase(fit);
        } else {
            if ((size_t) m_end + n > dr::width(m_data)) {
                // (host memory is reserved generously at once: the pages no block has written
                // stay out of the process's memory, and no copy of the tables is made as they grow)
                size_t first = dr::backend_v<Float> == JitBackend::LLVM ? (size_t) 1 << 28 : (size_t) 1 << 16;
                size_t cap = std::min<size_t>(std::max({ (size_t) m_end + n, 2 * dr::width(m_data), first }),
                                              UINT32_MAX);
                bool had = dr::width(m_data) > 0;
                m_data = copy(cap);
                if constexpr (dr::is_jit_v<Float>)
                    if (had) { // (the old array is not kept for reuse)
                        dr::sync_thread();
                        jit_flush_malloc_cache();
                    }
            }
            m_end += n;
        }
        // written in place (a scatter from a copy of the values kept that copy's memory in
        // Dr.Jit's cache, a load's blocks each their own)
        if constexpr (dr::is_jit_v<Float>) {
            dr::eval(m_data);
            dr::sync_thread();
            // (copy on write, as Dr.Jit's scatter: an expression that still reads the array,
            // traced before an update and not yet evaluated, keeps the values it was traced with)
            if (jit_var_ref(m_data.index()) > 1)
                m_data = copy(dr::width(m_data));
            auto plain = dr::detach(m_data);
            float *p = plain.data(); // (an array not yet written becomes memory here: kept)
            m_data = plain;
            jit_memcpy(dr::backend_v<Float>, p + at, values.data(), n * sizeof(float));
        } else {
            std::copy(values.begin(), values.end(), m_data.data() + at);
        }
        m_live += n;
        return at;
    }
    void free(uint32_t at, uint32_t n) {
        std::lock_guard<std::mutex> guard(m_mutex);
        m_live -= n;
        if (m_live == 0) {
            m_data = Storage();
            m_free.clear();
            m_end = 0;
            return;
        }
        auto next = m_free.find(at + n);
        if (next != m_free.end()) {
            n += next->second;
            m_free.erase(next);
        }
        auto prev = m_free.lower_bound(at);
        if (prev != m_free.begin() && std::prev(prev)->first + std::prev(prev)->second == at) {
            --prev;
            at = prev->first;
            n += prev->second;
            m_free.erase(prev);
        }
        if (at + n == m_end)
            m_end = at; // (the end is not a hole)
        else
            m_free[at] = n;
    }
    std::mutex m_mutex;
    Storage m_data;
    uint32_t m_end = 0;
    size_t m_live = 0;
    std::map<uint32_t, uint32_t> m_free; ///< offset → size
};

/// Every entry of the data tensors that `obj`'s traverse() shows, its children's included
/// (bitmap texels, grid voxels, in any precision): `f(values, channels)` per tensor, the
/// values on the host as floats.
/// A tensor's values on the host as floats (any precision; one read-back in the JIT variants).
template <typename Tensor> std::vector<float> host_floats(const Tensor &t) {
    using F32 = dr::float32_array_t<typename Tensor::Array>;
    F32 v = F32(t.array());
    return host_lanes(v, dr::width(v));
}

template <typename Float, typename F> void for_each_stored_tensor(Object *obj, F &&f) {
    using T = CoreAliases<Float>;
    std::unordered_set<Object *> seen{ obj };
    auto value = [&](std::string_view, void *ptr, const std::type_info &type) {
        auto take = [&](auto *tag) { // (a null pointer of the tensor's type)
            using Tensor = std::remove_pointer_t<decltype(tag)>;
            if (type != typeid(Tensor))
                return false;
            const Tensor &t = *static_cast<const Tensor *>(ptr);
            f(host_floats(t), t.ndim() > 0 ? t.shape(t.ndim() - 1) : (size_t) 1);
            return true;
        };
        (void) (take((typename T::TensorXf *) nullptr) || take((typename T::TensorXf16 *) nullptr) ||
                take((typename T::TensorXf64 *) nullptr));
    };
    visit(obj, value, [&](std::string_view, Object *o) { return o && seen.insert(o).second; });
}

/// The stored values of a texture or volume (for_each_stored_tensor), checked one by one:
/// each must be finite and, where the tensor holds the values themselves (`ranged`: not a
/// spectral variant's sigmoid coefficients), within [lo, hi]. The first bad one is named
/// with its index; the grid's or bitmap's maximum alone let a NaN or negative voxel through.
template <typename Float>
void check_stored_values(const char *plugin, const char *name, Object *obj, double lo, double hi,
                         bool ranged_multichannel) {
    for_each_stored_tensor<Float>(obj, [&](const std::vector<float> &v, size_t channels) {
        bool ranged = channels == 1 || ranged_multichannel;
        for (size_t i = 0; i < v.size(); ++i) {
            double x = v[i];
            if (!std::isfinite(x) || (ranged && !(x >= lo && x <= hi)))
                Throw("%s: invalid parameter \"%s\": value %zu (channel %zu) = %g: valid range is %s", plugin,
                      name, i, i % channels, x,
                      ranged ? tfm::format("[%g, %g]", lo, hi) : std::string("any finite number"));
        }
    });
}

/// The values a constant `value_at(wavelengths)` takes: at 48 wavelengths spread over Mitsuba's
/// 360–830 nm in spectral variants (12 calls of four), once in RGB; each finite and within [lo, hi].
template <typename Float, typename Spectrum, typename Eval>
void check_probed_values(const char *plugin, const char *name, double lo, double hi, Eval &&value_at) {
    using Wavelength = wavelength_t<Spectrum>;
    constexpr size_t calls = is_spectral_v<Spectrum> ? 12 : 1;
    for (size_t c = 0; c < calls; ++c) {
        Wavelength w = dr::zeros<Wavelength>();
        if constexpr (is_spectral_v<Spectrum>)
            for (size_t j = 0; j < dr::size_v<Wavelength>; ++j)
                w[j] = (float) (360.0 + 470.0 * (double) (c + calls * j) /
                                            (double) (calls * dr::size_v<Wavelength> - 1));
        auto value = value_at(w);
        for (size_t j = 0; j < dr::size_v<decltype(value)>; ++j) {
            double x = (double) dr::slice(value[j], 0);
            if (!(x >= lo && x <= hi))
                Throw("%s: invalid parameter \"%s\" = %g %s: valid range is [%g, %g]", plugin, name, x,
                      is_spectral_v<Spectrum> ? tfm::format("at %g nm", (double) dr::slice(w[j], 0))
                                              : tfm::format("(channel %zu)", j),
                      lo, hi);
        }
    }
}

/// Check that a reflectance-like texture stays within [lo, hi]: every texel a bitmap
/// stores (finite; in range where it stores the values), a constant's value at the
/// wavelengths (check_probed_values), and its mean and maximum (what a procedural
/// texture reports). NaN, ±inf and out-of-range values are rejected naming the parameter,
/// since Mitsuba itself accepts any float and a NaN reflectance renders an all-NaN image.
template <typename Float, typename Spectrum>
void check_texture_range(const char *plugin, const char *name, const Texture<Float, Spectrum> *tex, double lo,
                         double hi) {
    if (!tex)
        return;
    auto check = [&](double v, const char *what) {
        if (!(v >= lo && v <= hi))
            Throw("%s: invalid parameter \"%s\" = %g (%s): valid range is [%g, %g]", plugin, name, v, what,
                  lo, hi);
    };
    double mean = 0.0, max = 0.0;
    bool has_mean = true, has_max = true;
    try { mean = (double) dr::slice(tex->mean()); } catch (const std::exception &) { has_mean = false; }
    try { max = (double) tex->max(); } catch (const std::exception &) { has_max = false; }
    if (has_mean)
        check(mean, "its mean");
    if (has_max)
        check(max, "its maximum");
    auto *t = const_cast<Texture<Float, Spectrum> *>(tex);
    check_stored_values<Float>(plugin, name, t, lo, hi, !is_spectral_v<Spectrum>);
    if (!tex->is_spatially_varying())
        check_probed_values<Float, Spectrum>(plugin, name, lo, hi, [&](const wavelength_t<Spectrum> &w) {
            SurfaceInteraction<Float, Spectrum> si = dr::zeros<SurfaceInteraction<Float, Spectrum>>();
            si.wavelengths = w;
            return tex->eval(si, true);
        });
}

/// Allowed range of the integrators' `lambda_min`, nm.
constexpr double LambdaMinLo = 200.0, LambdaMinHi = 360.0;

/// The integrators' `lambda_min` (nm): where spectrally defined emitters reach below the
/// camera's 360 nm, validated against [LambdaMinLo, LambdaMinHi].
inline double lambda_min_of(const char *plugin, const Properties &props) {
    double lambda_min = get_float(plugin, props, "lambda_min", 300.0);
    if (!(lambda_min >= LambdaMinLo && lambda_min <= LambdaMinHi))
        Throw("%s: invalid parameter \"lambda_min\" = %f: valid range is [%.0f, %.0f] nm", plugin, lambda_min,
              LambdaMinLo, LambdaMinHi);
    return lambda_min;
}

/// Reduced RGB transport's warning for an emitter whose radiance is mostly ultraviolet.
inline void warn_uv_emitter(const char *plugin, const char *variant, const Object *emitter) {
    std::string name = emitter->id().empty() ? std::string(emitter->class_name()) : std::string(emitter->id());
    Log(Warn, "%s (%s): emitter %s is mostly ultraviolet; reduced transport carries it in one UV band, which "
              "can misstate UV-excited fluorescence several times over (a narrow 365 nm lamp: ~5x too dark, see "
              "`fluo-rs saturated-report`). Give fluo_path basis \"auto\" (built from the lights' spectra) or render "
              "UV-lit scenes in a spectral variant.",
        plugin, variant, name);
}

/// Parse "a, b, c" (commas and/or spaces) into exactly N doubles.
template <size_t N>
std::array<double, N> parse_list(const char *plugin, const char *name, const std::string &text) {
    std::array<double, N> out{};
    std::string s = text;
    std::replace(s.begin(), s.end(), ',', ' ');
    const char *p = s.c_str();
    size_t n = 0;
    while (true) {
        while (*p == ' ' || *p == '\t' || *p == '\n')
            ++p;
        if (*p == '\0')
            break;
        char *end = nullptr;
        double v = std::strtod(p, &end);
        if (end == p || n == N)
            Throw("%s: parameter \"%s\" = \"%s\" must be a list of %zu numbers", plugin, name, text, N);
        out[n++] = v;
        p = end;
    }
    if (n != N)
        Throw("%s: parameter \"%s\" = \"%s\" must be a list of %zu numbers (got %zu)", plugin, name, text, N, n);
    return out;
}

/// The variants every plugin serves (register_plugin in fluo_bispectral.h registers each class
/// template for all of them); every other variant of the wheel gets a stub.
inline bool served_variant(std::string_view variant) {
    return variant == "scalar_rgb" || variant == "scalar_spectral" || variant == "llvm_ad_rgb" ||
           variant == "llvm_ad_spectral" || variant == "cuda_ad_rgb" || variant == "cuda_ad_spectral" ||
           variant == "scalar_spectral_polarized" || variant == "llvm_ad_spectral_polarized" ||
           variant == "cuda_ad_spectral_polarized";
}

/// Register, for every variant of the wheel (MI_VARIANTS) that the plugins do not
/// serve, a factory that raises a clear error naming the plugin and the variant:
/// without it Mitsuba reports a plugin "not found", as if fluo were not loaded.
inline void register_unavailable(const char *name, ObjectType type) {
    struct Unavailable {
        std::string name, variant;
    };
    static std::deque<Unavailable> entries; // stable addresses: the factories' payloads
    std::string_view all = MI_VARIANTS;
    while (!all.empty()) {
        size_t end = all.find('\n');
        std::string_view variant = all.substr(0, end);
        all = end == std::string_view::npos ? std::string_view() : all.substr(end + 1);
        if (variant.empty() || served_variant(variant))
            continue;
        entries.push_back({ name, std::string(variant) });
        PluginManager::instance()->register_plugin(
            name, variant, type,
            [](void *payload, const Properties &) -> ref<Object> {
                auto *u = static_cast<const Unavailable *>(payload);
                Throw("%s: not available in variant \"%s\"; fluo's plugins run in scalar_rgb, "
                      "scalar_spectral, scalar_spectral_polarized, llvm_ad_rgb, llvm_ad_spectral, "
                      "llvm_ad_spectral_polarized and the cuda_ad ones of those (e.g. "
                      "mi.set_variant(\"scalar_spectral\"))",
                      u->name, u->variant);
            },
            nullptr, &entries.back());
    }
}

NAMESPACE_END(fluo_detail)

/// A texture that knows its emission spectrum (fluo_illuminant), so that reduced
/// transport can use the spectrum's own basis coefficients, including the UV band.
class SpectralSource {
public:
    virtual ~SpectralSource() = default;
    virtual const fluo::Illuminant &illuminant() const = 0;
    /// Luminance of the RGB value the texture evaluates to in the RGB variants (never 0).
    virtual double rgb_luminance() const = 0;
};

NAMESPACE_END(mitsuba)
