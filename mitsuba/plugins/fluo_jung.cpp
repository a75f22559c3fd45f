// fluo_jung, one class template for every variant it serves (the documentation below).
//
// Rust validates the parameters and bakes, at load and in parameters_changed(): the RGB
// parts and, through fluo_path, the reduced matrices. Per lane the plugin evaluates Jung's
// closed forms (fluo_forms.h; excitation wavelengths drawn by inverting the absorption
// b-spline's CDF) with Dr.Jit types, so gradients reach c, Q, λe, s and the reflectance.
#include <mitsuba/core/fresolver.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/texture.h>

#include <optional>
#include <vector>

#include "fluo_common.h"
#include "fluo_bispectral.h"
#include "fluo_jung_color.h"
#include "fluo_lambertian.h"

NAMESPACE_BEGIN(mitsuba)

/**!

.. _bsdf-fluo_jung:

Diffuse fluorescent material (:monosp:`fluo_jung`)
--------------------------------------------------

.. pluginparameters::

 * - reflectance
   - |spectrum| or |texture|
   - Reflectance r(λ) of the non-fluorescent (elastic) part. (Default: 0.5)
     Mutually exclusive with ``coefficients``.
 * - coefficients
   - |string|
   - Alternative to ``reflectance``: Jakob–Hanika sigmoid-polynomial coefficients
     "c0, c1, c2" with r(λ) = S(c0 λ² + c1 λ + c2), λ in nm (Jung et al. 2019, eq. 2).
 * - emission_peak
   - |float| or |texture|
   - Emission peak wavelength λe in nm, in [200, 1200]. (Default: 520)
 * - stokes_shift
   - |float| or |texture|
   - Stokes shift s in nm (distance from absorption peak to emission peak), in
     [0.001, s_max) where s_max keeps 2λe − s > 0 and the absorption band above 1 nm.
     (Default: 60)
 * - concentration
   - |float| or |texture|
   - Fluorophore concentration (mixing factor) c in [0, 1]. c = 0 is exactly
     Mitsuba's ``diffuse``. (Default: 0.5)
 * - quantum_yield
   - |float| or |texture|
   - Quantum yield Q in [0, 1]. (Default: 0.96, the paper's fixed value)
 * - color
   - |rgb| or |texture|
   - Wide-gamut RGB upsampling (Jung et al. 2019, sec. 3-4): a colour in
     ``color_space`` with components in [0, 1], given as ``<rgb name="color" .../>``, or a
     ``bitmap`` texture with ``raw=true`` whose texels are linear RGB in ``color_space``
     (an EXR; ``raw`` keeps Mitsuba from upsampling or gamma-decoding it). It is
     converted to a smooth reflectance plus just enough fluorescence (λe, c, s; Q = 0.96)
     through a coefficient cube: once for a constant colour, once per texel at load for
     a texture (nearest texel at render time, or see ``texel_interpolation``; ``wrap_mode``
     repeat, ``to_uv`` ignored).
     Mutually exclusive with ``reflectance``, ``coefficients``, ``emission_peak``,
     ``stokes_shift``, ``concentration`` and ``quantum_yield`` (the cube sets them).
 * - color_space
   - |string|
   - Space of ``color``: ``srgb`` (linear), ``rec2020`` or ``acescg``. (Default: acescg)
 * - cube
   - |string|
   - Coefficient cube file (``fluo upsample-cube``). (Default: the shipped
     ``data/cubes/<color_space>_d65_tinf_r33.cube``; ``$FLUO_CUBE_DIR`` overrides the directory)
 * - lookup
   - |string|
   - ``nearest`` cube entry, or ``trilinear`` interpolation of coefficients (λe and s
     only over corners with c > 0, the paper's rule). (Default: nearest, which the
     paper finds less disruptive at the onset of fluorescence)
 * - texel_interpolation
   - |string|
   - For a ``color`` texture: ``nearest`` texel, or ``bilinear``: the four texels around
     the hit mixed with bilinear weights in the elastic part and the reradiation (Jung
     et al. 2019, Fig. 12: interpolate the texels' reradiation rather than their
     coefficients; ``fluo_path`` picks one texel's dye per vertex with its weight in the
     spectral variants, an unbiased estimate of the mixture). (Default: nearest)
 * - fluorescence
   - |bool|
   - ``false`` uses the cube's reflectance-only solutions (for comparisons). (Default: true)

The diffuse fluorescent BBRRDF of Jung, Hanika & Dachsbacher (2018), as used by
Jung et al., "Wide Gamut Spectral Upsampling with Fluorescence" (CGF 2019), eq. 1:

.. math::

    f(λ_i, ω_i, ω_o, λ_o) = \frac{δ(λ_i − λ_o)(1 − c\,a(λ_i))\,r(λ_i) + c\,a(λ_i)\,Q\,e(λ_o)}{π}

with a b-spline emission spectrum e (unit integral, eq. 5) and an absorption spectrum
a (peak 1, eq. 6) that mirrors it over wavenumber, touching but not overlapping it.
The physics (equations, sampling, validation) lives in the Rust core, ``core/src/models/jung.rs``.

What this plugin computes, in every variant it serves (``scalar_*``, ``llvm_ad_*``,
``cuda_ad_*``; one class, ``fluo_jung.cpp``): Rust validates the parameters and bakes, at
load and after every ``mi.traverse`` update, the dye's absorption table (which samples
excitation wavelengths; the weights use the closed forms, so the estimator stays
unbiased), the RGB parts and the reduced matrices; per lane the plugin evaluates Jung's
closed forms (b-spline emission, absorption mirrored over wavenumber, the sigmoid) and
Mitsuba's reflectance texture with Dr.Jit types. No variant calls Rust per vertex.

- Spectral variants: the BSDF interface serves the elastic part
  (1 − c a(λ)) r(λ) / π at each hero wavelength, like ``diffuse`` otherwise
  (cosine-weighted sampling). The reradiation c a(λi) Q e(λo) / π is served through
  fluo's bispectral interface (``BispectralBSDF`` in ``include/fluo/fluo_bispectral.h``) to the
  wavelength-shifting ``fluo_path`` and ``fluo_volpath`` integrators; under Mitsuba's
  ``path`` the absorbed light is simply lost (a warning says so once per scene).
- RGB variants: the albedo the model implies under an equal-energy light, converted
  to linear sRGB the way Mitsuba converts reflectance spectra (CIE 1931, 360–830 nm):
  sRGB[r (1 − c a)] + k sRGB[c Q e ∫a], where negative channels (a saturated emission
  outside the sRGB gamut) are clipped at zero and k ≤ 1 is the largest factor keeping
  every channel ≤ 1: under equal-energy light a fluorescent green can out-reflect white
  in the green channel, but an RGB integrator cannot take that energy from the other
  channels, and a channel above 1 would gain energy in a closed furnace. With a
  textured ``reflectance`` the elastic part is approximated per channel as
  texture ⊙ sRGB(1 − c a)/sRGB(1) (exact for constant r), bounded the same way per hit;
  a ``color`` bitmap serves each texel's albedo. Under ``fluo_path`` the RGB
  variants instead transport fluorescence with reduced reradiation matrices.

**Textured parameters.** ``emission_peak``, ``stokes_shift``, ``concentration`` and
``quantum_yield`` each take a float texture (a one-channel ``bitmap``, a ``checkerboard``,
...), read per hit with the texture's own ``eval_1`` (its ``to_uv`` and filter), as
Mitsuba's plugins read float textures. The model is the one of the hit's parameters in
every variant and integrator: the reradiation c·Q·a(λi)·e(λo) is linear in c and Q and
the elastic part (1 − c·a) r linear in c, so the plugin builds one dye shape (a, e) per
(λe, s) pair at load and scales it per hit (``fluo_path``: per-hit wavelength shifting in
the spectral variants; in the RGB variants each shape's reduced matrix, computed once,
times c·Q, plus the hit's elastic part; Mitsuba's own integrators: the hit's albedo as for
a uniform material). A filtered lookup between texels interpolates c and Q (exactly
the interpolated material, by linearity); λe and s take the nearest of the texture's
validated values (emission shapes are not blended: use ``filter_type=nearest`` for
them). What is validated at load, with the same ranges as the floats: every texel of a
bitmap (NaN and out-of-range values are named with their texel, e.g. ``"concentration" =
1.5 at texel (x = 3, y = 7)``), the constituent values of a texture made of others (a
checkerboard's ``color0``/``color1``), and every (λe, s) pair the two textures can
combine (at most 4096 pairs). A ``concentration`` or ``quantum_yield`` texture whose
values cannot be read (a procedural texture without texture children) is checked
through its mean and maximum, and a hit's value is clamped to [0, 1]; such textures are
refused for ``emission_peak`` and ``stokes_shift``. A parameter given as a float, or as a
texture that does not vary, takes the uniform material's code path unchanged. With
``coefficients`` the textured material's elastic part is the hit's r(1 − c a): in the
RGB variants its sRGB (transported as a per-band albedo), where a uniform material's
reduced matrix carries it spectrally.

**Gradients** (``llvm_ad_*``, ``cuda_ad_*``). ``mi.traverse`` exposes ``concentration``,
``quantum_yield``, ``emission_peak``, ``stokes_shift`` and the ``reflectance`` texture as
differentiable parameters: in the spectral variants gradients reach all of them through the
closed forms; in the RGB ones the reduced operator is M_r − c·M_ra + c·Q·M_fl (exact in c
and Q, so their gradients and the reflectance's are exact) and the dye's shape (λe, s)
reaches it through the derivatives of the reduced matrices and RGB parts
(jit_reduced_derivatives: central differences of the reductions). Textured parameters are
differentiable per texel where the texture's own values are (a ``bitmap``'s ``data``): c
and Q scale the hit's dye shape; for λe and s each hit's shape is its nearest level, which
carries the texture's derivative at that level: in the spectral variants the closed forms'
derivative in λe or s, in the RGB ones (``fluo_path``, ``fluo_prb``) each shape's ∂M/∂λe and
∂M/∂s and its RGB parts' derivatives, central differences of its reductions, computed when a
render begins only where such a texture's values carry gradients (Mitsuba's own RGB
integrators, which see the albedo alone, get no dye-shape derivative of a texture). The
shapes are the textures' distinct (λe, s) pairs, at most 4096: an optimisation that makes
every texel of a λe texture distinct works up to 4096 texels (64 × 64; fewer with a
varying s), each shape reduced again at every render. With
``filter_type=nearest`` that is the derivative of the image; a filtered lookup between
texels of different levels gives the derivative of the unquantised material. A ``color``
texture's texels (each texel's dye, sigmoid and RGB albedo gathered per lane; its
excitation wavelength sampled from the texel's absorption band) are not differentiable.
Textured numeric parameters: per lane λe and s take the nearest of the texture's validated
levels (binary search over them), c and Q the texture's value clamped to [0, 1]; in the RGB
variants each dye shape's reduced
reradiation matrix (at c = Q = 1, reduced once per render) is gathered per lane and scaled
by c·Q, the elastic part being the hit's RGB albedo. ``texel_interpolation = bilinear``
mixes the four texels' elastic albedos with their weights and, in the spectral variants,
draws one of them by its weight for the reradiation (unbiased for the mixture).

Invalid parameters (negative yield, a Stokes shift that breaks 2λe − s > 0, both
``reflectance`` and ``coefficients``, colours outside [0, 1], NaN texels, an unknown
``color_space``, a malformed cube) raise an error naming the parameter, its value
and the valid range.

The cube's colours are those of the reflected light under CIE D65 (360–830 nm),
Bradford-adapted to the space's white; see ``core/src/upsample/``. In the RGB variants the
upsampled material is shown as Mitsuba shows any reflectance spectrum (sRGB under E).

.. tabs::
    .. code-tab:: xml
        :name: fluo-jung

        <bsdf type="fluo_jung">
            <rgb name="reflectance" value="0.6, 0.6, 0.6"/>
            <float name="emission_peak" value="520"/>
            <float name="stokes_shift" value="80"/>
            <float name="concentration" value="0.8"/>
        </bsdf>

    .. code-tab:: xml
        :name: fluo-jung-textured

        <bsdf type="fluo_jung">
            <float name="reflectance" value="0.8"/>
            <texture type="bitmap" name="concentration">
                <string name="filename" value="textures/label_concentration.png"/>
                <boolean name="raw" value="true"/>
            </texture>
            <texture type="checkerboard" name="emission_peak">
                <float name="color0" value="520"/>
                <float name="color1" value="610"/>
            </texture>
        </bsdf>

    .. code-tab:: xml
        :name: fluo-jung-color

        <bsdf type="fluo_jung">
            <rgb name="color" value="0.9, 0, 0.9"/>
            <string name="color_space" value="acescg"/>
        </bsdf>

    .. code-tab:: python

        'type': 'fluo_jung',
        'coefficients': '0.0, 0.0, 2.0',
        'emission_peak': 610.0,
        'stokes_shift': 90.0
*/

template <typename Float, typename Spectrum>
class FluoJung final : public BSDF<Float, Spectrum>, public fluo_detail::BispectralBSDF<Float, Spectrum> {
public:
    MI_IMPORT_BASE(BSDF, m_flags, m_components)
    MI_IMPORT_TYPES(Texture)
    using WMask = dr::mask_t<UnpolarizedSpectrum>;
    using Dye = fluo_detail::JungDye<UnpolarizedSpectrum>;
    using fluo_detail::BispectralBSDF<Float, Spectrum>::MaxTerms;
    using Choice = typename fluo_detail::BispectralBSDF<Float, Spectrum>::Choice;
    using Bispectral = fluo_detail::BispectralBSDF<Float, Spectrum>;
    using Joined = typename Bispectral::Joined;

    static constexpr const char *Plugin = "fluo_jung";
    FluoJung(const Properties &props) : Base(props) {
        using namespace fluo_detail;
        // A numeric parameter is a float (differentiable) or a float texture (per lane).
        jung_param_textures(Plugin, props, m_config, m_param_tex);
        if (props.has_property("color"))
            init_color(props);
        else
            m_reflectance = jung_reflectance<Texture>(Plugin, props, m_config);
        for (auto [value, field] : params())
            *value = (ScalarFloat) *field;
        m_flags = BSDFFlags::DiffuseReflection | BSDFFlags::FrontSide;
        m_components.push_back(m_flags);
        rebuild();
    }

    /// The numeric parameters' members and configuration fields (fluo_detail::JungParamNames' order).
    std::array<std::pair<Float *, double *>, fluo_detail::JungParams> params() {
        return { { { &m_peak, &m_config.emission_peak }, { &m_shift, &m_config.stokes_shift },
                   { &m_conc, &m_config.concentration }, { &m_yield, &m_config.quantum_yield } } };
    }

    void traverse(TraversalCallback *cb) override {
        m_record.arm(this);
        Base::traverse(cb);
        if (m_color_mode)
            return; // everything derives from the colour and the cube
        if (m_reflectance)
            cb->put("reflectance", m_reflectance, ParamFlags::Differentiable);
        for (size_t i = 0; i < fluo_detail::JungParams; ++i) {
            if (m_param_tex[i]) // a texture: its values select the dye shapes baked at load and,
                // per texel, carry gradients (docs: "Gradients")
                cb->put(fluo_detail::JungParamNames[i], m_param_tex[i], ParamFlags::Differentiable);
            else
                cb->put(fluo_detail::JungParamNames[i], *params()[i].first, ParamFlags::Differentiable);
        }
    }

    void parameters_changed(const std::vector<std::string> &keys) override {
        // The JIT values keep their AD graph; Rust sees their detached values and
        // re-bakes the tables (a textured parameter's texture is read again). A refused
        // update puts every traversed value back (fluo_detail::UpdateRecord).
        m_record.update(this, m_config, [&] {
            for (size_t i = 0; i < fluo_detail::JungParams; ++i)
                if (auto [value, field] = params()[i]; !m_param_tex[i])
                    *field = fluo_detail::updated_param(Plugin, fluo_detail::JungParamNames[i], *value, *field);
            if (m_reflectance) // a texture updated in place: its values must stay in [0, 1]
                fluo_detail::check_texture_range(Plugin, "reflectance", m_reflectance.get(), 0.0, 1.0);
            rebuild();
        });
        Base::parameters_changed(keys);
    }

    FLUO_LAMBERTIAN_BSDF_METHODS(albedo(si, active), this->warn_if_unmanaged(Plugin))

    // ------------------------------------------------ fluo_path's interface (fluo_bispectral.h)
    bool jit_uniform() const override {
        return !m_texels && !m_shapes && (!m_reflectance || !m_reflectance->is_spatially_varying());
    }
    bool jit_fluorescent() const override {
        if (m_texels) // RGB: a colour texture is a plain BSDF (the colour the cube reproduces)
            return is_spectral_v<Spectrum> && fluo::jung_texture_is_fluorescent(**m_texture);
        if (m_shapes)
            return m_shapes->fluoresce;
        // c·Q = 0 re-emits nothing, but with gradients on c or Q its derivative does
        return fluo::jung_is_fluorescent(**m_model) || gradient_only();
    }
    /// c·Q = 0 with gradients on c or Q: the dye's bands from its closed forms (Rust's
    /// ranges are empty for a dye that re-emits nothing).
    /// λe or s carry gradients (a uniform dye in a JIT AD variant): RGB then adds the
    /// derivatives of what it bakes from them (jit_reduced_derivatives, the RGB parts).
    bool shape_gradients() const {
        bool one_shape = !m_shapes || (!m_param_tex[fluo_detail::JungPeak] && !m_param_tex[fluo_detail::JungShift]);
        return one_shape && !m_texels && (dr::grad_enabled(m_peak) || dr::grad_enabled(m_shift));
    }
    /// One dye shape at `cfg`'s (λe, s).
    static rust::Box<fluo::JungShapes> unit_dye(const fluo::JungConfig &cfg) {
        return fluo::jung_shapes_new(rust::Slice<const double>(&cfg.emission_peak, 1),
                                     rust::Slice<const double>(&cfg.stokes_shift, 1));
    }
    /// What RGB bakes from the dye's shape at `cfg` (fluo::jung_rgb_parts with this base):
    /// reflectance_absorbed, absorbed_scale, fluorescence (9 values).
    std::vector<double> rgb_parts_at(const fluo::JungConfig &cfg) const {
        fluo::JungRgbParts q = fluo::jung_rgb_parts(fluo::jung_shapes_model(*unit_dye(cfg), 0), **m_model);
        return { q.reflectance_absorbed.r, q.reflectance_absorbed.g, q.reflectance_absorbed.b,
                 q.absorbed_scale.r,       q.absorbed_scale.g,       q.absorbed_scale.b,
                 q.fluorescence.r,         q.fluorescence.g,         q.fluorescence.b };
    }
    /// A dye shape's unit reradiation at `cfg`'s (λe, s), reduced (K×K, Lambertian).
    static std::vector<double> shape_operator(const fluo::JungConfig &cfg, const fluo::TransportBasis &transport) {
        size_t kk = fluo::transport_size(transport) * fluo::transport_size(transport);
        std::vector<double> out(kk);
        auto u = unit_dye(cfg);
        auto reduced = fluo::reduced_new(fluo::jung_fluorescence(fluo::jung_shapes_model(*u, 0)), transport);
        if (!fluo::reduced_lambertian(*reduced, rust::Slice<double>(out.data(), kk)))
            Throw("%s: a dye shape has no Lambertian reduced operator", Plugin);
        return out;
    }
    /// ∂f/∂λe (i = 0) or ∂f/∂s (i = 1) of a host computation f(config) at `base` (default:
    /// the material's) by central differences with a 0.25 nm step (one-sided at a range end,
    /// where Rust refuses the step; zeros where neither side is valid).
    template <typename F>
    std::vector<double> shape_derivative(size_t i, F &&f, const fluo::JungConfig *base = nullptr) const {
        auto at = [&](double delta) -> std::optional<std::vector<double>> {
            fluo::JungConfig cfg = base ? *base : m_config;
            (i == 0 ? cfg.emission_peak : cfg.stokes_shift) += delta;
            try {
                return f(cfg);
            } catch (const std::exception &) {
                return std::nullopt; // outside the parameter's range
            }
        };
        std::optional<std::vector<double>> d = fluo_detail::central_difference(0.25, at);
        return d ? *d : std::vector<double>(at(0.0).value_or(std::vector<double>()).size(), 0.0);
    }

    bool gradient_only() const {
        return !m_shapes && !m_texels && !fluo::jung_is_fluorescent(**m_model) &&
               (dr::grad_enabled(m_conc) || dr::grad_enabled(m_yield));
    }
    fluo_detail::JungDye<double> host_dye() const {
        return fluo_detail::JungDye<double>(m_config.emission_peak, m_config.stokes_shift);
    }
    fluo::Range jit_emission_range() const override {
        if (m_shapes) { // the union of the dye shapes' emission
            fluo::Range r{ 1e30, -1e30 };
            for (size_t i = 0; i < fluo::jung_shapes_len(**m_shapes->shapes); ++i) {
                fluo::Range ri = fluo::fluo_emission_range(fluo::jung_fluorescence(shape(i)));
                r = { std::min(r.lo, ri.lo), std::max(r.hi, ri.hi) };
            }
            return r;
        }
        if (gradient_only())
            return { host_dye().peak - host_dye().alpha, host_dye().peak + host_dye().alpha };
        return fluo::fluo_emission_range(fluo::jung_fluorescence(
            m_texels ? fluo::jung_texture_representative(**m_texture) : **m_model));
    }
    fluo::Range jit_excitation_range() const override {
        if (m_shapes || m_texels)
            return { 0.0, 1e30 };
        if (gradient_only())
            return { host_dye().lo, host_dye().edge };
        return fluo::fluo_excitation_range(fluo::jung_fluorescence(**m_model));
    }
    /// M = M_r − c·M_ra + c·Q·M_fl (fluo::jung_reduced_parts): exact for every c and Q.
    /// Textured parameters: none here (jit_reduced_table holds the dye shapes' reradiation,
    /// the elastic part is the hit's RGB albedo).
    bool jit_reduced_matrices(const fluo::TransportBasis &transport,
                              std::array<std::vector<double>, MaxTerms> &m) const override {
        if (m_texels)
            Throw("%s: a \"color\" texture has no reduced operator (it renders as its RGB albedo)", Plugin);
        if (m_shapes)
            return false; // (m stays 0)
        auto slice = [](std::vector<double> &v) { return rust::Slice<double>(v.data(), v.size()); };
        return fluo::jung_reduced_parts(**m_model, transport, slice(m[0]), slice(m[1]), slice(m[2]));
    }
    std::array<Float, MaxTerms> jit_reduced_weights() const override {
        return { Float(1.f), -m_conc, m_conc * m_yield };
    }

    /// RGB with gradients on λe or s (one dye shape): a uniform dye's A = M_0 − c·M_1(λe, s) +
    /// c·Q·M_2(λe, s), so ∂A/∂λe = −c·∂M_1/∂λe + c·Q·∂M_2/∂λe (and for s); with a textured c
    /// or Q the hit's c·Q times ∂M/∂λe of the shape's unit reradiation M (jit_reduced_table).
    /// Central differences of the reductions (shape_derivative).
    size_t jit_reduced_derivatives(const fluo::TransportBasis &transport,
                                   std::vector<std::vector<double>> &d) const override {
        if (!shape_gradients())
            return 0;
        size_t kk = fluo::transport_size(transport) * fluo::transport_size(transport);
        d.resize(2);
        double c = m_config.concentration, q = m_config.quantum_yield;
        for (size_t i = 0; i < 2; ++i)
            d[i] = shape_derivative(i, [&](const fluo::JungConfig &cfg) {
                if (m_shapes)
                    return shape_operator(cfg, transport);
                std::vector<double> r(kk), a(kk), e(kk), out(kk);
                auto model = fluo::jung_new(cfg);
                fluo::jung_reduced_parts(*model, transport, rust::Slice<double>(r.data(), kk),
                                         rust::Slice<double>(a.data(), kk), rust::Slice<double>(e.data(), kk));
                for (size_t j = 0; j < kk; ++j)
                    out[j] = -c * a[j] + c * q * e[j];
                return out;
            });
        return 2;
    }
    std::vector<Float> jit_reduced_derivative_weights(const SurfaceInteraction3f &si, Mask active) const override {
        Float scale = m_shapes ? jit_reduced_select(si, active).second : Float(1.f); // (textured: c·Q)
        return { (m_peak - dr::detach(m_peak)) * scale, (m_shift - dr::detach(m_shift)) * scale };
    }

    /// Textured parameters: each dye shape's reduced reradiation at c = Q = 1, one per
    /// (λe, s) pair; a hit uses its shape's, times c·Q.
    size_t jit_reduced_table(const fluo::TransportBasis &transport, std::vector<double> &m) const override {
        if (!m_shapes)
            return 0;
        size_t n = fluo::jung_shapes_len(**m_shapes->shapes), k = fluo::transport_size(transport);
        m.assign(n * k * k, 0.0);
        for (size_t i = 0; i < n; ++i) {
            auto r = fluo_detail::rust_call(
                Plugin, [&] { return fluo::reduced_new(fluo::jung_fluorescence(shape(i)), transport); });
            if (!fluo::reduced_lambertian(*r, rust::Slice<double>(m.data() + i * k * k, k * k)))
                Throw("%s: dye shape %zu has no Lambertian reduced operator", Plugin, i);
        }
        return n;
    }
    std::pair<UInt32, Float> jit_reduced_select(const SurfaceInteraction3f &si, Mask active) const override {
        Hit h = hit(si, active);
        return { h.shape, h.t.conc * h.t.yield };
    }
    /// RGB, a λe or s texture whose values carry gradients: each dye shape's ∂M/∂λe and
    /// ∂M/∂s (central differences of its reductions, shape_derivative's step) and the
    /// derivatives of its RGB parts (textured_elastic); a hit adds them times its
    /// level's θ − detach(θ) (hit(): the texture's derivative there) and c·Q.
    size_t jit_reduced_table_derivatives(const fluo::TransportBasis &transport,
                                         std::vector<double> &d) const override {
        m_shape_d = 0;
        if (!textured_shape_gradients())
            return 0;
        size_t n = fluo::jung_shapes_len(**m_shapes->shapes), kk = fluo::transport_size(transport);
        kk *= kk;
        constexpr size_t NP = ShapeFields - SReflectanceAbsorbed;
        d.assign(2 * n * kk, 0.0);
        std::vector<float> dparts[2][NP];
        for (size_t i = 0, ns = m_shapes->shifts.size(); i < n; ++i) {
            fluo::JungConfig cfg = m_config; // shape i's (λe, s), peak-major
            cfg.emission_peak = m_shapes->peaks[i / ns];
            cfg.stokes_shift = m_shapes->shifts[i % ns];
            for (size_t p = 0; p < 2; ++p) {
                auto op = [&](const fluo::JungConfig &c) { return shape_operator(c, transport); };
                auto parts = [&](const fluo::JungConfig &c) { return rgb_parts_at(c); };
                std::vector<double> dm = shape_derivative(p, op, &cfg), dq = shape_derivative(p, parts, &cfg);
                if (dm.size() == kk)
                    std::copy(dm.begin(), dm.end(), d.begin() + (p * n + i) * kk);
                for (size_t f = 0; f < NP; ++f)
                    dparts[p][f].push_back(dq.size() == NP ? (float) dq[f] : 0.f);
            }
        }
        for (size_t p = 0; p < 2; ++p)
            for (size_t f = 0; f < NP; ++f)
                m_shape_dparts[p][f] = dr::load<FloatStorage>(dparts[p][f].data(), n);
        m_shape_d = 2;
        return 2;
    }
    std::vector<Float> jit_reduced_select_derivatives(const SurfaceInteraction3f &si, Mask active) const override {
        if (m_shape_d == 0)
            return {};
        Hit h = hit(si, active);
        Float cq = h.t.conc * h.t.yield;
        return { (h.t.peak - dr::detach(h.t.peak)) * cq, (h.t.shift - dr::detach(h.t.shift)) * cq };
    }
    /// RGB AD variants with a λe or s texture: whether the dye shapes' derivatives are
    /// needed, i.e. a texture's own values carry gradients (a bitmap's data, a
    /// checkerboard's colours) or the other parameter, a float, does (shape_gradients()
    /// serves one shape only).
    bool textured_shape_gradients() const {
        if constexpr (!dr::is_diff_v<Float> || is_spectral_v<Spectrum>) {
            return false;
        } else {
            if (!m_shapes || m_texels ||
                (!m_param_tex[fluo_detail::JungPeak] && !m_param_tex[fluo_detail::JungShift]))
                return false;
            if ((!m_param_tex[fluo_detail::JungPeak] && dr::grad_enabled(m_peak)) ||
                (!m_param_tex[fluo_detail::JungShift] && dr::grad_enabled(m_shift)))
                return true;
            bool any = false;
            auto value = [&](std::string_view, void *ptr, const std::type_info &type) {
                if (type == typeid(Float))
                    any |= dr::grad_enabled(*(const Float *) ptr);
                else if (type == typeid(TensorXf))
                    any |= dr::grad_enabled(*(const TensorXf *) ptr);
                else if (type == typeid(Color3f))
                    any |= dr::grad_enabled(*(const Color3f *) ptr);
            };
            for (auto p : { fluo_detail::JungPeak, fluo_detail::JungShift })
                if (m_param_tex[p]) // (reads only)
                    fluo_detail::visit(const_cast<Texture *>(m_param_tex[p].get()), value,
                                       [](std::string_view, Object *o) { return o != nullptr; });
            return any;
        }
    }

    UnpolarizedSpectrum jit_elastic_albedo(const SurfaceInteraction3f &si, Mask active) const override {
        if (m_texels)
            return texel_elastic(si, active);
        if (m_shapes)
            return textured_elastic(si, hit(si, active), active);
        if constexpr (is_rgb_v<Spectrum>) {
            if (m_reflectance)
                return m_reflectance->eval(si, active) * absorbed_factor(m_conc, m_rgb_absorbed_scale);
            return dr::clip(m_rgb_reflectance - m_conc * m_rgb_reflectance_absorbed, 0.f, 1.f);
        } else {
            return reflectance(si, active) * (1.f - m_conc * Dye(m_peak, m_shift).absorption(si.wavelengths));
        }
    }

    Choice jit_choose(const SurfaceInteraction3f &si, const Wavelength &u1, const Wavelength &u2, double range_lo,
                      double range_hi, Mask active) const override {
        const Wavelength &lambda_o = si.wavelengths;
        if constexpr (!is_spectral_v<Spectrum>) {
            return this->elastic_only(lambda_o);
        } else {
            // Probabilities are detached: gradients flow through the values only.
            Wavelength u2p = u2; // (its first number also picks a texel, then rescaled)
            Texel t = m_texels   ? texel(pick_texel(si, u2p[0]), active)
                      : m_shapes ? hit(si, active).t
                                 : Texel{ m_peak, m_shift, m_conc, m_yield };
            if (m_texels)
                fluo_detail::rotate_hero(u2p); // uniform again given the texel
            UnpolarizedSpectrum albedo = jit_elastic_albedo(si, active), we = dr::maximum(dr::detach(albedo), 0.f);
            return choose_dye(t, we, albedo, lambda_o, u1, u2p, range_lo, range_hi, active);
        }
    }

    /// Many materials: a uniform dye without gradients joins the others of its class as a
    /// row of λe, s, c, Q and its reflectance at ChoiceNodes wavelengths over Mitsuba's
    /// 360-830 nm (the elastic weight of the choice: any positive value where the elastic
    /// part is positive keeps the estimate unbiased, so the reflectance is read linearly
    /// between the nodes there, exact at them).
    static constexpr size_t ChoiceNodes = 24, RowWidth = 4 + ChoiceNodes;
    bool jit_joinable() const override {
        if (!is_spectral_v<Spectrum> || !jit_uniform() || !jit_fluorescent() || dr::grad_enabled(m_peak) ||
            dr::grad_enabled(m_shift) || dr::grad_enabled(m_conc) || dr::grad_enabled(m_yield))
            return false;
        // (a reflectance with gradients: traced, not evaluated)
        return !dr::grad_enabled(reflectance(dr::zeros<SurfaceInteraction3f>(), true));
    }
    Joined jit_join(const std::vector<const Bispectral *> &members) const override {
        if constexpr (!is_spectral_v<Spectrum>) {
            (void) members;
            return nullptr;
        } else {
            std::vector<float> rows;
            for (const Bispectral *b : members) {
                const auto *m = static_cast<const FluoJung *>(b);
                SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>(ChoiceNodes / 4);
                for (size_t w = 0; w < 4; ++w)
                    si.wavelengths[w] = MI_CIE_MIN + (MI_CIE_MAX - MI_CIE_MIN) / (ChoiceNodes - 1) *
                                                         Float(dr::arange<UInt32>(ChoiceNodes / 4) * 4u + (uint32_t) w);
                UnpolarizedSpectrum r = dr::detach(m->reflectance(si, true));
                dr::eval(r); // (one kernel for the four hero wavelengths' nodes)
                for (float v : { dr::slice(m->m_peak), dr::slice(m->m_shift), dr::slice(m->m_conc),
                                 dr::slice(m->m_yield) })
                    rows.push_back(v);
                size_t at = rows.size();
                rows.resize(at + ChoiceNodes);
                for (size_t w = 0; w < 4; ++w) { // (a reflectance folded to one lane: broadcast)
                    std::vector<float> v = fluo_detail::host_lanes(r[w], ChoiceNodes / 4);
                    for (size_t i = 0; i < ChoiceNodes / 4; ++i)
                        rows[at + 4 * i + w] = v[i];
                }
            }
            return std::make_shared<const DynamicBuffer<Float>>(
                dr::load<DynamicBuffer<Float>>(rows.data(), rows.size()));
        }
    }
    Choice jit_choose_joined(const Joined &joined, const UInt32 &member, const SurfaceInteraction3f &si,
                             const Wavelength &u1, const Wavelength &u2, double range_lo, double range_hi,
                             Mask active) const override {
        if constexpr (!is_spectral_v<Spectrum>) {
            (void) joined, (void) member, (void) u1, (void) u2, (void) range_lo, (void) range_hi, (void) active;
            return this->elastic_only(si.wavelengths);
        } else {
            const auto &rows = *static_cast<const DynamicBuffer<Float> *>(joined.get());
            UInt32 base = member * (uint32_t) RowWidth;
            auto at = [&](uint32_t k) { return fluo_detail::fetch<Float>(rows, base + k, active); };
            Texel t{ at(0), at(1), at(2), at(3) };
            UnpolarizedSpectrum r;
            for (size_t w = 0; w < dr::size_v<UnpolarizedSpectrum>; ++w) {
                Float x = dr::clip((si.wavelengths[w] - MI_CIE_MIN) * ((ChoiceNodes - 1) / (MI_CIE_MAX - MI_CIE_MIN)),
                                   0.f, (float) (ChoiceNodes - 1));
                UInt32 j = dr::minimum(UInt32(x), (uint32_t) ChoiceNodes - 2);
                r[w] = dr::lerp(fluo_detail::fetch<Float>(rows, base + 4u + j, active),
                                fluo_detail::fetch<Float>(rows, base + 5u + j, active), x - Float(j));
            }
            UnpolarizedSpectrum we = dr::maximum(r * (1.f - t.conc * Dye(t.peak, t.shift).absorption(si.wavelengths)), 0.f);
            return choose_dye(t, we, UnpolarizedSpectrum(-1.f), si.wavelengths, u1, u2, range_lo, range_hi, active);
        }
    }

    std::string to_string() const override {
        std::ostringstream oss;
        oss << "FluoJung[" << std::endl
            << "  model = " << std::string(fluo::jung_to_string(**m_model)) << "," << std::endl;
        if (m_reflectance)
            oss << "  reflectance = " << string::indent(m_reflectance) << "," << std::endl;
        if (m_color_mode)
            oss << "  color = " << m_color_text << "," << std::endl;
        for (size_t i = 0; i < fluo_detail::JungParams; ++i)
            if (m_param_tex[i])
                oss << "  " << fluo_detail::JungParamNames[i] << " = " << string::indent(m_param_tex[i]) << ","
                    << std::endl;
        if (m_shapes)
            oss << "  dye shapes = " << fluo::jung_shapes_len(**m_shapes->shapes)
                << " ((emission_peak, stokes_shift) pairs)," << std::endl;
        oss << "  evaluation = closed forms per lane" << std::endl << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(FluoJung)

private:
    /// Per-texel parameters (m_texel_data) in this order.
    enum TexelField { TPeak, TShift, TConc, TYield, TC0, TC1, TC2, TR, TG, TB, TexelFields };
    using FloatStorage = DynamicBuffer<Float>;

    /// A hit's dye: λe, s, c, Q.
    struct Texel {
        Float peak, shift, conc, yield;
    };

    /// A textured material's parameters at a hit (hit()).
    struct Hit {
        UInt32 shape; ///< peak-major index of the (λe, s) pair
        Texel t;
    };

    /// jit_choose for the dye t with elastic weight `we` (`albedo`: the Choice's elastic albedo, or −1);
    /// spectral variants (its callers return elastic_only in RGB).
    Choice choose_dye(const Texel &t, const UnpolarizedSpectrum &we, const UnpolarizedSpectrum &albedo,
                      const Wavelength &lambda_o, const Wavelength &u1, const Wavelength &u2p, double range_lo,
                      double range_hi, const Mask &active) const {
        using Band = fluo_detail::JungDye<Float>; // (one value per lane; Dye: per wavelength)
        Dye dye(dr::detach(t.peak), dr::detach(t.shift));
        Band band(dr::detach(t.peak), dr::detach(t.shift));
        // The excitation range: the dye's absorption band inside the lights' range, as
        // an interval of the b-spline coordinate v (decreasing in λ).
        Float lo = dr::maximum(band.lo, (float) range_lo), hi = dr::minimum(band.edge, (float) range_hi);
        Mask overlap = active && hi > lo;
        Float v_a = dr::clip(band.v_of(dr::select(overlap, hi, band.edge)), 0.f, 6.f),
              v_b = dr::clip(band.v_of(dr::select(overlap, lo, band.lo)), 0.f, 6.f);
        Float cdf_a = Band::bspline_cdf(v_a), mass = dr::select(overlap, Band::bspline_cdf(v_b) - cdf_a, 0.f);
        // w_f ≈ c·Q·e(λo)·∫a over the range (∫b dv times |dλ/dv| at the absorption peak):
        // any positive value where the shift integrand is positive keeps the estimate
        // unbiased; a close one keeps the variance low.
        Float jacobian = dr::rcp(band.dv_dlambda(band.peak - dr::detach(t.shift)));
        // With gradients on c or Q, c·Q has a floor in this weight: at c = 0 (or Q = 0) the
        // shift would never be drawn and d/dc of the reradiation c·Q·a·e would be lost.
        Float cq = dr::detach(t.conc * t.yield);
        if (dr::grad_enabled(t.conc) || dr::grad_enabled(t.yield))
            cq = dr::maximum(cq, fluo_detail::GradientShiftFloor);
        UnpolarizedSpectrum wf = dr::select(mass > 0.f, cq * dye.emission(lambda_o) * (mass * jacobian), 0.f);
        fluo_detail::ShiftChoice<UnpolarizedSpectrum> choice(we, wf, u1, active);
        if constexpr (!dr::is_jit_v<Float>) // (scalar variants draw λi only where a shift is taken)
            if (dr::none(choice.shifted))
                return { lambda_o, choice.weight(UnpolarizedSpectrum(0.f), u1), choice.shifted,
                         UnpolarizedSpectrum(0.f), UInt32(0), albedo };
        WMask &shifted = choice.shifted;
        // v ∝ b(v − 3) on [v_a, v_b] by inverting its CDF in closed form (no table, no
        // search: the dye's parameters stay kernel inputs), mapped to λi;
        // pdf(λi) = b(v − 3)/mass·|dv/dλ|.
        Wavelength v = Dye::bspline_cdf_inverse(cdf_a + u2p * mass);
        Wavelength lambda_i = dye.lambda_of(v);
        UnpolarizedSpectrum pdf_i = Dye::bspline(v - 3.f) / mass * dye.dv_dlambda(lambda_i);
        UnpolarizedSpectrum scale = choice.weight(pdf_i, u1);
        // π·f_fl(λi, λo) = c·Q·a(λi)·e(λo), with the parameters' gradients.
        Dye exact(t.peak, t.shift);
        UnpolarizedSpectrum rerad = t.conc * t.yield * exact.absorption(lambda_i) * exact.emission(lambda_o);
        rerad = dr::select(shifted && lambda_i < lambda_o, rerad, 0.f);
        return { dr::select(shifted, lambda_i, lambda_o), scale, shifted, rerad, UInt32(0), albedo };
    }

    /// Validate in Rust and bake what the lanes read.
    void rebuild() {
        using namespace fluo_detail;
        m_shape_d = 0; // (the shapes may change: their derivatives are made again when a render begins)
        // textured parameters: every texture's values validated (Rust names a bad texel) and one
        // dye shape per (λe, s) pair (fluo_jung_color.h); the levels of λe and s on the device,
        // for the per-lane nearest level
        m_shapes = jung_shape_set(Plugin, m_param_tex, m_config);
        if (m_shapes) {
            m_peak_levels = dr::load<FloatStorage>(m_shapes->peaks.data(), m_shapes->peaks.size());
            m_shift_levels = dr::load<FloatStorage>(m_shapes->shifts.data(), m_shapes->shifts.size());
        }
        m_model = rust_call(Plugin, [&] { return fluo::jung_new(m_config); });
        m_unit = rust_call(Plugin, [&] { return unit_dye(m_config); });
        const fluo::JungModel &unit = fluo::jung_shapes_model(**m_unit, 0);
        if constexpr (is_rgb_v<Spectrum>) {
            auto color = [](const fluo::Rgb &c) { return Color3f((float) c.r, (float) c.g, (float) c.b); };
            fluo::JungRgbParts p = fluo::jung_rgb_parts(unit, **m_model);
            m_rgb_reflectance = color(p.reflectance);
            m_rgb_reflectance_absorbed = color(p.reflectance_absorbed);
            m_rgb_absorbed_scale = color(p.absorbed_scale);
            m_rgb_fluorescence = color(p.fluorescence);
            // with gradients on λe or s: the parts' derivatives along them (rgb_parts_at's order),
            // added times θ − detach(θ) (zero in value) to the uniform parts and to a single dye
            // shape's gathered ones
            const bool derive = shape_gradients();
            Float delta[2] = { m_peak - dr::detach(m_peak), m_shift - dr::detach(m_shift) };
            std::vector<double> dparts[2];
            for (size_t i = 0; derive && i < 2; ++i) {
                dparts[i] = shape_derivative(i, [&](const fluo::JungConfig &cfg) { return rgb_parts_at(cfg); });
                const std::vector<double> &g = dparts[i];
                auto part = [&](size_t o) { return Color3f((float) g[o], (float) g[o + 1], (float) g[o + 2]); };
                m_rgb_reflectance_absorbed += delta[i] * part(0);
                m_rgb_absorbed_scale += delta[i] * part(3);
                m_rgb_fluorescence += delta[i] * part(6);
            }
            if (m_shapes) { // per dye shape, gathered per lane
                size_t n = fluo::jung_shapes_len(**m_shapes->shapes);
                std::vector<float> parts[ShapeFields]; // [part][channel] of each shape
                for (size_t i = 0; i < n; ++i) {
                    fluo::JungRgbParts q = fluo::jung_rgb_parts(shape(i), **m_model);
                    size_t k = 0;
                    for (const fluo::Rgb *c :
                         { &q.reflectance, &q.reflectance_absorbed, &q.absorbed_scale, &q.fluorescence })
                        for (double v : { c->r, c->g, c->b })
                            parts[k++].push_back((float) v);
                }
                for (size_t f = 0; f < ShapeFields; ++f)
                    m_shape_parts[f] = dr::load<FloatStorage>(parts[f].data(), n);
                for (size_t i = 0; derive && i < 2; ++i) // (one shape; fields 0..2, reflectance, hold no dye)
                    for (size_t f = 3; f < ShapeFields; ++f)
                        m_shape_parts[f] = m_shape_parts[f] + FloatStorage(delta[i] * (float) dparts[i][f - 3]);
            }
        }
        for (size_t i = 0; i < 3; ++i)
            m_coef[i] = (ScalarFloat) (i == 0 ? m_config.c0 : i == 1 ? m_config.c1 : m_config.c2);
        // Values, not literals, in the JIT variants: a literal is compiled into each
        // instance's callable, so materials differing in a value each made their own (200
        // dyes: a 60 s first render); opaque, all instances share one (as Mitsuba's plugins do).
        dr::make_opaque(m_peak, m_shift, m_conc, m_yield, m_coef[0], m_coef[1], m_coef[2], m_rgb_reflectance,
                        m_rgb_reflectance_absorbed, m_rgb_absorbed_scale, m_rgb_fluorescence);
    }

    const fluo::JungModel &shape(size_t i) const { return fluo::jung_shapes_model(**m_shapes->shapes, i); }

    /// A textured material's dye at a hit: λe and s the nearest of their validated levels
    /// (every shape a hit uses was built at load), c and Q the textures' values clamped to
    /// [0, 1] (not finite: 0), read with each texture's own eval_1.
    Hit hit(const SurfaceInteraction3f &si, Mask active) const {
        using namespace fluo_detail;
        auto level = [&](JungParam p, const FloatStorage &levels, size_t n, const Float &uniform) {
            if (!m_param_tex[p]) // its one level: the (differentiable) float
                return std::make_pair(UInt32(0), uniform);
            Float x = m_param_tex[p]->eval_1(si, active);
            UInt32 i(0);
            if (n > 1) {
                i = dr::binary_search<UInt32>(1, (uint32_t) n - 1, [&](const UInt32 &k) {
                        return fluo_detail::fetch<Float>(levels, k, active) <= x;
                    }) - 1;
                Float a = fluo_detail::fetch<Float>(levels, i, active), b = fluo_detail::fetch<Float>(levels, i + 1, active);
                i = dr::select(dr::isnan(x), 0u, dr::select(x - a <= b - x, i, i + 1));
            }
            Float v = fluo_detail::fetch<Float>(levels, i, active);
            // a texture with gradients (its texels): the level carries the hit's value's
            // derivative (x − detach(x) is 0 in value), i.e. the derivative in λe or s at the
            // level (spectral: the closed forms'; RGB: the shape's derivative tables,
            // jit_reduced_table_derivatives) times the texture's in its texels
            if (dr::grad_enabled(x))
                v += dr::select(dr::isfinite(x), x - dr::detach(x), 0.f);
            return std::make_pair(i, v);
        };
        auto unit = [&](JungParam p, const Float &uniform) {
            if (!m_param_tex[p])
                return uniform;
            Float v = m_param_tex[p]->eval_1(si, active);
            return dr::select(dr::isfinite(v), dr::clip(v, 0.f, 1.f), 0.f);
        };
        auto [ip, peak] = level(JungPeak, m_peak_levels, m_shapes->peaks.size(), m_peak);
        auto [is, shift] = level(JungShift, m_shift_levels, m_shapes->shifts.size(), m_shift);
        return { ip * (uint32_t) m_shapes->shifts.size() + is,
                 Texel{ peak, shift, unit(JungConc, m_conc), unit(JungYield, m_yield) } };
    }

    /// A textured material's elastic albedo at a hit: r(λ)(1 − c a(λ)) of its dye (spectral);
    /// in RGB its shape's parts (with a reflectance texture, the texture times
    /// sRGB(1 − c a)/sRGB(1), else clipped to [0, 1]).
    UnpolarizedSpectrum textured_elastic(const SurfaceInteraction3f &si, const Hit &h, Mask active) const {
        if constexpr (is_rgb_v<Spectrum>) {
            auto part = [&](size_t f) {
                Color3f v(fluo_detail::fetch<Float>(m_shape_parts[f], h.shape, active),
                          fluo_detail::fetch<Float>(m_shape_parts[f + 1], h.shape, active),
                          fluo_detail::fetch<Float>(m_shape_parts[f + 2], h.shape, active));
                if (m_shape_d > 0 && f >= SReflectanceAbsorbed) { // + δλe·∂/∂λe + δs·∂/∂s (0 in value)
                    Float delta[2] = { h.t.peak - dr::detach(h.t.peak), h.t.shift - dr::detach(h.t.shift) };
                    for (size_t d = 0; d < 2; ++d)
                        for (size_t c = 0; c < 3; ++c)
                            v[c] = dr::fmadd(delta[d],
                                             fluo_detail::fetch<Float>(m_shape_dparts[d][f - SReflectanceAbsorbed + c],
                                                               h.shape, active),
                                             v[c]);
                }
                return v;
            };
            if (m_reflectance)
                return m_reflectance->eval(si, active) * absorbed_factor(h.t.conc, part(SAbsorbedScale));
            return dr::clip(part(SReflectance) - h.t.conc * part(SReflectanceAbsorbed), 0.f, 1.f);
        } else {
            return reflectance(si, active) * (1.f - h.t.conc * Dye(h.t.peak, h.t.shift).absorption(si.wavelengths));
        }
    }

    /// RGB: a reflectance texture's factor 1 − c·s clipped to [0, 1] (s = sRGB(a)/sRGB(1) per
    /// channel, negative where the dye's absorption projects negatively: 1 there). Written
    /// as a select on s rather than a clip: at c ≈ 0, 1 − c·s rounds to 1 and a clip's tie
    /// dropped d/dc (AD 0.0118 against 0.0086 by differences below c = 1e-5).
    static Color3f absorbed_factor(const Float &c, const Color3f &s) {
        return dr::select(s > 0.f, dr::maximum(1.f - c * s, 0.f), 1.f);
    }

    /// r(λ): the reflectance texture, or the sigmoid of the coefficients.
    UnpolarizedSpectrum reflectance(const SurfaceInteraction3f &si, Mask active) const {
        if (m_reflectance)
            return m_reflectance->eval(si, active);
        if constexpr (is_spectral_v<Spectrum>)
            return fluo_detail::sigmoid_polynomial(si.wavelengths, m_coef[0], m_coef[1], m_coef[2]);
        else
            return m_rgb_reflectance;
    }

    /// The albedo served to Mitsuba: the elastic part in spectral variants; in RGB ones the
    /// elastic part plus c·Q times the unit reradiation under equal-energy light, bounded
    /// per channel (fluo::colour::bounded_rgb_albedo's rule: negative
    /// channels of each part clipped, the reradiation scaled by the largest k ≤ 1 keeping
    /// every channel ≤ 1).
    UnpolarizedSpectrum albedo(const SurfaceInteraction3f &si, Mask active) const {
        if (m_texels)
            return texel_elastic(si, active);
        if constexpr (is_rgb_v<Spectrum>) {
            Color3f e = dr::clip(jit_elastic_albedo(si, active), 0.f, 1.f);
            Color3f f = dr::maximum(m_conc * m_yield * m_rgb_fluorescence, 0.f);
            if (m_shapes) { // the hit's dye shape, c and Q
                Hit h = hit(si, active);
                Color3f unit(fluo_detail::fetch<Float>(m_shape_parts[SFluorescence], h.shape, active),
                             fluo_detail::fetch<Float>(m_shape_parts[SFluorescence + 1], h.shape, active),
                             fluo_detail::fetch<Float>(m_shape_parts[SFluorescence + 2], h.shape, active));
                f = dr::maximum(h.t.conc * h.t.yield * unit, 0.f);
            }
            Float k = 1.f;
            for (size_t c = 0; c < 3; ++c)
                k = dr::select(f[c] > 0.f, dr::minimum(k, (1.f - e[c]) / f[c]), k);
            k = dr::maximum(k, 0.f);
            return dr::minimum(e + k * f, 1.f);
        } else {
            return jit_elastic_albedo(si, active);
        }
    }

    /// `color` (a constant <rgb>): the cube's dye and sigmoid.
    void init_color(const Properties &props) {
        using namespace fluo_detail;
        JungColorOptions o = jung_color_options(Plugin, props);
        m_color_mode = true;
        const std::string &space = o.space, &cube_file = o.cube_file, &lookup = o.lookup;
        bool use_fluorescence = o.fluorescence;
        m_bilinear = o.bilinear;
        auto cube = rust_call(Plugin, [&] { return fluo::upsample_cube_load(space, cube_file); });
        if (o.texture) {
            init_color_texture(props.get_texture<Texture>("color"), *cube, space, lookup, use_fluorescence);
            return;
        }
        ScalarColor3f c = props.get<ScalarColor3f>("color");
        std::array<double, 3> rgb = { (double) c[0], (double) c[1], (double) c[2] };
        m_color_text = tfm::format("(%g, %g, %g) %s", rgb[0], rgb[1], rgb[2], space);
        m_config = rust_call(Plugin, [&] {
            return fluo::upsample_lookup(*cube, rust::Slice<const double>(rgb.data(), 3), lookup, use_fluorescence);
        });
    }

    /// A `color` texture: every texel's model, looked up once at load (Rust, the cube), and
    /// its parameters as arrays gathered per lane at the hit's texels (texels_at; repeat
    /// wrap). The texels are read with the texture's own eval_3 at texel centres: one wide
    /// call in the llvm/cuda variants, one call per texel in the scalar ones.
    void init_color_texture(const ref<Texture> &tex, const fluo::UpsampleCube &cube, const std::string &space,
                            const std::string &lookup, bool use_fluorescence) {
        using namespace fluo_detail;
        if (!tex->is_spatially_varying())
            Throw("%s: \"color\" is a constant texture; give it as <rgb name=\"color\" value=\"r, g, b\"/> "
                  "(or as a raw bitmap texture)", Plugin);
        ScalarVector2i res = tex->resolution();
        if (!(res.x() > 0 && res.y() > 0))
            Throw("%s: \"color\" texture has no texels", Plugin);
        size_t w = (size_t) res.x(), h = (size_t) res.y(), n = w * h;
        std::vector<float> texels(3 * n);
        try {
            if constexpr (dr::is_jit_v<Float>) { // one wide call
                UInt32 i = dr::arange<UInt32>((uint32_t) n);
                SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>(n);
                si.uv = Point2f((Float(i % (uint32_t) w) + .5f) / (float) w,
                                (Float(i / (uint32_t) w) + .5f) / (float) h);
                Color3f v = tex->eval_3(si, true);
                for (size_t k = 0; k < 3; ++k) { // planar, reordered below
                    std::vector<float> channel = host_lanes(v[k], n);
                    std::copy(channel.begin(), channel.end(), texels.begin() + (std::ptrdiff_t) (k * n));
                }
            } else { // one call per texel
                SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>();
                for (size_t t = 0; t < n; ++t) {
                    si.uv = Point2f(((float) (t % w) + .5f) / (float) w, ((float) (t / w) + .5f) / (float) h);
                    Color3f v = tex->eval_3(si, true);
                    for (size_t k = 0; k < 3; ++k)
                        texels[k * n + t] = v[k];
                }
            }
        } catch (const std::exception &e) {
            Throw("%s: cannot read the \"color\" texture's RGB texels (it must be a 3-channel "
                  "bitmap with <boolean name=\"raw\" value=\"true\"/>, holding linear %s): %s",
                  Plugin, space, e.what());
        }
        std::vector<float> rgb(3 * n);
        for (size_t t = 0; t < n; ++t)
            for (size_t k = 0; k < 3; ++k)
                rgb[3 * t + k] = texels[k * n + t];
        m_texture = rust_call(Plugin, [&] {
            return fluo::jung_texture_new(cube, w, h, rust::Slice<const float>(rgb.data(), rgb.size()), lookup,
                                          use_fluorescence);
        });
        m_color_text = tfm::format("texture %zu x %zu %s, %zu distinct coefficient sets, %s texels", w, h, space,
                                   fluo::jung_texture_distinct(**m_texture), m_bilinear ? "bilinear" : "nearest");
        std::vector<float> fields[TexelFields];
        for (auto &f : fields)
            f.resize(n);
        for (size_t t = 0; t < n; ++t) {
            int64_t x = (int64_t) (t % w), y = (int64_t) (t / w);
            const fluo::JungModel &m = fluo::jung_texture_model(**m_texture, x, y);
            fluo::JungConfig c = fluo::jung_config(m);
            fluo::Rgb a = fluo::jung_texture_rgb(**m_texture, x, y);
            double values[TexelFields] = { c.emission_peak, c.stokes_shift, c.concentration, c.quantum_yield,
                                           c.c0, c.c1, c.c2, a.r, a.g, a.b };
            for (size_t k = 0; k < TexelFields; ++k)
                fields[k][t] = (float) values[k];
        }
        for (size_t k = 0; k < TexelFields; ++k)
            m_texel_data[k] = dr::load<FloatStorage>(fields[k].data(), n);
        m_res = res;
        m_texels = true;
        m_config = fluo::jung_config(fluo::jung_texture_representative(**m_texture)); // for rebuild()
    }

    /// Texel (x, y) of a colour texture, repeat wrap.
    UInt32 texel_at(const Int32 &x, const Int32 &y) const {
        auto wrap = [](const Int32 &i, int size) {
            Int32 r = i % size;
            return UInt32(dr::select(r < 0, r + size, r));
        };
        return wrap(y, m_res.y()) * (uint32_t) m_res.x() + wrap(x, m_res.x());
    }

    /// The texels a hit reads and their weights (summing to 1): its nearest texel, or with
    /// texel_interpolation = bilinear the four around si.uv (texel centres) with bilinear
    /// weights (Jung et al. 2019, Fig. 12: interpolate the texels' reradiation, not their
    /// coefficients). uv that is not finite reads texel 0.
    struct TexelSet {
        UInt32 index[4];
        Float weight[4];
        size_t n = 1;
    };
    TexelSet texels_at(const SurfaceInteraction3f &si) const {
        TexelSet ts;
        Mask finite = dr::isfinite(si.uv.x()) && dr::isfinite(si.uv.y());
        if (!m_bilinear) {
            Float u = dr::select(finite, dr::floor(si.uv.x() * (float) m_res.x()), 0.f),
                  v = dr::select(finite, dr::floor(si.uv.y() * (float) m_res.y()), 0.f);
            ts.index[0] = texel_at(Int32(u), Int32(v));
            ts.weight[0] = 1.f;
            return ts;
        }
        Float u = dr::select(finite, dr::fmadd(si.uv.x(), (float) m_res.x(), -.5f), 0.f),
              v = dr::select(finite, dr::fmadd(si.uv.y(), (float) m_res.y(), -.5f), 0.f);
        Float fu = dr::floor(u), fv = dr::floor(v), tu = u - fu, tv = v - fv;
        ts.n = 4;
        for (int a = 0; a < 2; ++a)
            for (int b = 0; b < 2; ++b) {
                ts.index[2 * a + b] = texel_at(Int32(fu) + a, Int32(fv) + b);
                ts.weight[2 * a + b] = (a ? tu : 1.f - tu) * (b ? tv : 1.f - tv);
            }
        return ts;
    }

    Float texel_field(TexelField k, const UInt32 &index, Mask active) const {
        return fluo_detail::fetch<Float>(m_texel_data[k], index, active);
    }

    Texel texel(const UInt32 &i, Mask active) const {
        return { texel_field(TPeak, i, active), texel_field(TShift, i, active), texel_field(TConc, i, active),
                 texel_field(TYield, i, active) };
    }

    /// The texel whose dye a shift at this hit uses: one of texels_at(si) drawn with its
    /// weight by u (then rescaled to a fresh uniform number): the reradiation estimated
    /// from the drawn texel's dye is unbiased for the weighted mixture.
    UInt32 pick_texel(const SurfaceInteraction3f &si, Float &u) const {
        TexelSet ts = texels_at(si);
        UInt32 index = ts.index[0];
        Float lo = 0.f, w = ts.weight[0], cum = ts.weight[0];
        for (size_t j = 1; j < ts.n; ++j) {
            dr::mask_t<Float> take = u >= cum && ts.weight[j] > 0.f;
            index = dr::select(take, ts.index[j], index);
            lo = dr::select(take, cum, lo);
            w = dr::select(take, ts.weight[j], w);
            cum += ts.weight[j];
        }
        u = dr::select(w > 0.f, dr::clip((u - lo) / w, 0.f, dr::OneMinusEpsilon<Float>), u);
        return index;
    }

    /// A colour texture's elastic albedo: r(λ)(1 − c a(λ)) of the texel's sigmoid and dye
    /// (spectral), or the texel's RGB albedo (RGB variants, as the cube reproduces it);
    /// bilinear texels mix their texels' albedos.
    UnpolarizedSpectrum texel_elastic(const SurfaceInteraction3f &si, Mask active) const {
        TexelSet ts = texels_at(si);
        UnpolarizedSpectrum out(0.f);
        for (size_t j = 0; j < ts.n; ++j) {
            const UInt32 &i = ts.index[j];
            if constexpr (is_rgb_v<Spectrum>) {
                out += ts.weight[j] *
                       Color3f(texel_field(TR, i, active), texel_field(TG, i, active), texel_field(TB, i, active));
            } else {
                Dye dye(texel_field(TPeak, i, active), texel_field(TShift, i, active));
                UnpolarizedSpectrum r = fluo_detail::sigmoid_polynomial(si.wavelengths, texel_field(TC0, i, active),
                                                                        texel_field(TC1, i, active),
                                                                        texel_field(TC2, i, active));
                out += ts.weight[j] * r * (1.f - texel_field(TConc, i, active) * dye.absorption(si.wavelengths));
            }
        }
        return out;
    }

    fluo::JungConfig m_config = fluo::jung_default_config(); ///< the defaults live in Rust
    fluo_detail::UpdateRecord<Float> m_record; ///< the traversed values, as last accepted
    std::optional<rust::Box<fluo::JungModel>> m_model;      ///< validated at every rebuild
    std::optional<rust::Box<fluo::JungShapes>> m_unit;      ///< the dye at c = Q = 1
    ref<Texture> m_reflectance;                              ///< null: sigmoid coefficients
    Float m_peak, m_shift, m_conc, m_yield;                  ///< λe, s, c, Q (differentiable)
    Float m_coef[3];                                         ///< the sigmoid's coefficients
    Color3f m_rgb_reflectance = 0.f, m_rgb_reflectance_absorbed = 0.f, m_rgb_absorbed_scale = 0.f,
            m_rgb_fluorescence = 0.f; ///< RGB variant: fluo::JungRgbParts of the unit dye
    bool m_color_mode = false;
    std::string m_color_text;
    bool m_texels = false;   ///< a `color` texture: per-texel dyes (below)
    bool m_bilinear = false; ///< ... read with bilinear weights (else the nearest texel)
    std::optional<rust::Box<fluo::JungTexture>> m_texture;
    FloatStorage m_texel_data[TexelFields];
    ScalarVector2i m_res = ScalarVector2i(0, 0);
    // textured numeric parameters (null: the float members)
    ref<Texture> m_param_tex[fluo_detail::JungParams];
    std::optional<fluo_detail::JungShapeSet> m_shapes; ///< their levels and dye shapes
    FloatStorage m_peak_levels, m_shift_levels;        ///< the levels of λe and s, sorted
    /// RGB variant: per dye shape, fluo::JungRgbParts (reflectance, reflectance_absorbed,
    /// absorbed_scale, fluorescence; 3 channels each)
    enum ShapeField {
        SReflectance = 0,
        SReflectanceAbsorbed = 3,
        SAbsorbedScale = 6,
        SFluorescence = 9,
        ShapeFields = 12
    };
    FloatStorage m_shape_parts[ShapeFields];
    /// RGB with gradients on a λe or s texture: per dye shape the derivatives of its parts
    /// from SReflectanceAbsorbed on (rgb_parts_at's order) along λe and s, and how many
    /// derivative tables its reduced operators have (jit_reduced_table_derivatives, set when
    /// a render begins: 0 or 2)
    mutable FloatStorage m_shape_dparts[2][ShapeFields - SReflectanceAbsorbed];
    mutable uint32_t m_shape_d = 0;

    MI_TRAVERSE_CB(Base, m_reflectance, m_peak, m_shift, m_conc, m_yield, m_rgb_reflectance,
                   m_rgb_reflectance_absorbed, m_rgb_absorbed_scale, m_rgb_fluorescence)
};

static const bool fluo_jung_jit_registered =
    (fluo_detail::register_plugin<FluoJung>("fluo_jung", ObjectType::BSDF), true);

NAMESPACE_END(mitsuba)
