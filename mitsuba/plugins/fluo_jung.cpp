#include <mitsuba/core/fresolver.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/core/warp.h>
#include <mitsuba/render/bsdf.h>
#include <mitsuba/render/texture.h>

#include <optional>
#include <vector>

#include "fluo_bispectral.h"
#include "fluo_common.h"
#include "fluo_jung_color.h"
#include "fluo_lambertian.h"
#include "fluo_param_texture.h"

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
     coefficients; ``fluo_path`` picks one texel's dye per vertex with its weight in
     ``scalar_spectral``, an unbiased estimate of the mixture). (Default: nearest)
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

What this plugin computes in each variant:

- ``scalar_spectral``: the BSDF interface serves the elastic part
  (1 − c a(λ)) r(λ) / π at each hero wavelength, like ``diffuse`` otherwise
  (cosine-weighted sampling). The reradiation c a(λi) Q e(λo) / π is served through
  fluo's bispectral interface (``include/fluo/fluo_bispectral.h``) to the wavelength-shifting
  ``fluo_path`` integrator; under Mitsuba's ``path`` the absorbed light is simply lost.
- ``scalar_rgb``: the albedo the model implies under an equal-energy light, converted
  to linear sRGB the way Mitsuba converts reflectance spectra (CIE 1931, 360–830 nm):
  sRGB[r (1 − c a)] + k sRGB[c Q e ∫a], where negative channels (a saturated emission
  outside the sRGB gamut) are clipped at zero and k ≤ 1 is the largest factor keeping
  every channel ≤ 1: under equal-energy light a fluorescent green can out-reflect white
  in the green channel, but an RGB integrator cannot take that energy from the other
  channels, and a channel above 1 would gain energy in a closed furnace. With a
  textured ``reflectance`` the elastic part is approximated per channel as
  texture ⊙ sRGB(1 − c a)/sRGB(1) (exact for constant r), bounded the same way per hit;
  a ``color`` bitmap serves each texel's bounded albedo. Under ``fluo_path`` the RGB
  variant instead transports fluorescence with reduced reradiation matrices.

**Textured parameters.** ``emission_peak``, ``stokes_shift``, ``concentration`` and
``quantum_yield`` each take a float texture (a one-channel ``bitmap``, a ``checkerboard``,
...), read per hit with the texture's own ``eval_1`` (its ``to_uv`` and filter), as
Mitsuba's plugins read float textures. The model is the one of the hit's parameters in
every variant and integrator: the reradiation c·Q·a(λi)·e(λo) is linear in c and Q and
the elastic part (1 − c·a) r linear in c, so the plugin builds one dye shape (a, e) per
(λe, s) pair at load and scales it per hit (``fluo_path``: per-hit wavelength shifting in
``scalar_spectral``; in ``scalar_rgb`` each shape's reduced matrix, computed once, times
c·Q, plus the hit's elastic part; Mitsuba's own integrators: the hit's albedo as for a
uniform material). A filtered lookup between texels interpolates c and Q (exactly
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
``coefficients`` the textured material's elastic part is the hit's r(1 − c a): in
``scalar_rgb`` its sRGB (transported as a per-band albedo), where a uniform material's
reduced matrix carries it spectrally.

**Vectorised variants** (``llvm_ad_rgb``, ``llvm_ad_spectral``; ``fluo_jung_jit.cpp``).
The same material, evaluated per lane with Dr.Jit types: Rust validates the parameters
and bakes, at load and after every ``mi.traverse`` update, the dye's absorption table
(which samples excitation wavelengths; the weights use the closed forms, so the estimator
stays unbiased), the RGB parts and the reduced matrices; per lane the shim evaluates
Jung's closed forms (b-spline emission, absorption mirrored over wavenumber, the sigmoid)
and Mitsuba's reflectance texture. Rendered with ``fluo_path`` it gives the scalar
variants' images within noise (``test_llvm.py``). ``mi.traverse`` exposes
``concentration``, ``quantum_yield``, ``emission_peak``, ``stokes_shift`` and the
``reflectance`` texture as differentiable parameters: in ``llvm_ad_spectral`` gradients
reach all of them; in ``llvm_ad_rgb`` the reduced operator is M_r − c·M_ra + c·Q·M_fl
(exact in c and Q, so their gradients and the reflectance's are exact), while the dye's
shape (λe, s) is baked into the reduced matrices per render and gets no gradient there.
A ``color`` texture works with nearest texels (each texel's dye, sigmoid and RGB
albedo gathered per lane; its excitation wavelength is sampled uniformly over the texel's
absorption band, weighted by the exact absorption: unbiased, a little noisier than the
scalar variants' exact inversion). Textured numeric parameters work as in the scalar
variants: per lane λe and s take the nearest of the texture's validated levels (binary
search over them), c and Q the texture's value clamped to [0, 1]; in ``llvm_ad_rgb`` each
dye shape's reduced reradiation matrix (at c = Q = 1, reduced once per render) is
gathered per lane and scaled by c·Q, the elastic part being the hit's RGB albedo, as in
``scalar_rgb``. A textured parameter is not differentiable (``mi.traverse`` lists its
texture; the floats stay differentiable). Not yet available in these variants (a clear
error at load): ``texel_interpolation = bilinear``.

Invalid parameters (negative yield, a Stokes shift that breaks 2λe − s > 0, both
``reflectance`` and ``coefficients``, colours outside [0, 1], NaN texels, an unknown
``color_space``, a malformed cube) raise an error naming the parameter, its value
and the valid range.

The cube's colours are those of the reflected light under CIE D65 (360–830 nm),
Bradford-adapted to the space's white; see ``core/src/upsample/``. In ``scalar_rgb`` the
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
class FluoJung final : public BSDF<Float, Spectrum>, public BispectralBSDF<Float, Spectrum> {
public:
    MI_IMPORT_BASE(BSDF, m_flags, m_components)
    MI_IMPORT_TYPES(Texture)

    static constexpr const char *Plugin = "fluo_jung";

    FluoJung(const Properties &props) : Base(props) {
        using namespace fluo_detail;
        // A numeric parameter is a float (the uniform fast path) or a float texture.
        jung_param_textures(Plugin, props, m_config, m_param_tex);
        if (props.has_property("color"))
            init_color(props);
        else
            m_reflectance = jung_reflectance<Texture>(Plugin, props, m_config);
        m_flags = BSDFFlags::DiffuseReflection | BSDFFlags::FrontSide;
        m_components.push_back(m_flags);
        rebuild();
    }

    void traverse(TraversalCallback *cb) override {
        if (m_color_mode)
            return; // everything derives from the colour and the cube
        if (m_reflectance)
            cb->put("reflectance", m_reflectance, ParamFlags::NonDifferentiable);
        ScalarFloat *values[NParams] = { &m_emission_peak, &m_stokes_shift, &m_concentration, &m_quantum_yield };
        for (size_t i = 0; i < NParams; ++i) {
            if (m_param_tex[i])
                cb->put(ParamNames[i], m_param_tex[i], ParamFlags::NonDifferentiable);
            else
                cb->put(ParamNames[i], *values[i], ParamFlags::NonDifferentiable);
        }
    }

    void parameters_changed(const std::vector<std::string> &keys) override {
        // Copy back only what changed, so untouched values keep their double precision.
        auto changed = [&](const char *name) {
            return keys.empty() || string::contains(keys, name);
        };
        // A textured parameter's texture may have changed too: rebuild() re-reads them all.
        fluo_detail::transactional_update(m_config, [&] {
            if (changed("emission_peak") && !m_param_tex[Peak])  m_config.emission_peak = m_emission_peak;
            if (changed("stokes_shift") && !m_param_tex[Shift])  m_config.stokes_shift  = m_stokes_shift;
            if (changed("concentration") && !m_param_tex[Conc])  m_config.concentration = m_concentration;
            if (changed("quantum_yield") && !m_param_tex[Yield]) m_config.quantum_yield = m_quantum_yield;
        }, [&] { rebuild(); });
    }

    FLUO_LAMBERTIAN_BSDF_METHODS(albedo(si, active), this->warn_if_unmanaged(Plugin))

    const fluo::Fluorescence *fluorescence() const override {
        if (m_shapes) {
            if (!m_shapes_fluoresce)
                return nullptr;
            return &fluo::jung_fluorescence(fluo::jung_shapes_model(**m_shapes, fluo::jung_shapes_representative(**m_shapes)));
        }
        if (m_texture_models) {
            if (!fluo::jung_texture_is_fluorescent(**m_texture_models))
                return nullptr;
            return &fluo::jung_fluorescence(fluo::jung_texture_representative(**m_texture_models));
        }
        return fluo::jung_is_fluorescent(**m_model) ? &fluo::jung_fluorescence(**m_model) : nullptr;
    }

    const fluo::Fluorescence *fluorescence_at(const SurfaceInteraction3f &si) const override {
        if (m_shapes) {
            typename BispectralBSDF<Float, Spectrum>::Mixture mix;
            fluorescence_local(si, mix);
            return mix[0].model;
        }
        if (!m_texture_models)
            return fluorescence();
        const fluo::JungModel &m = texel_model(si);
        return fluo::jung_is_fluorescent(m) ? &fluo::jung_fluorescence(m) : nullptr;
    }

    bool fluorescence_varies() const override { return m_texture_models.has_value() || m_shapes.has_value(); }

    /// Textured parameters: the dye shape of the hit's (λe, s), scaled by its c·Q.
    size_t fluorescence_local(const SurfaceInteraction3f &si,
                              typename BispectralBSDF<Float, Spectrum>::Mixture &out) const override {
        if (m_texture_models && m_texel_bilinear) {
            Texels t = texels_at(si);
            for (size_t i = 0; i < t.n; ++i) {
                const fluo::JungModel &m = fluo::jung_texture_model(**m_texture_models, t.x[i], t.y[i]);
                out[i] = { fluo::jung_is_fluorescent(m) ? &fluo::jung_fluorescence(m) : nullptr,
                           BispectralBSDF<Float, Spectrum>::NoIndex, 1.0, t.w[i] };
            }
            return t.n;
        }
        if (!m_shapes)
            return BispectralBSDF<Float, Spectrum>::fluorescence_local(si, out);
        Hit h = hit_params(si, true);
        double w = (double) h.c * (double) h.q;
        out[0] = { w > 0.0 ? &fluo::jung_fluorescence(shape(h.shape)) : nullptr, h.shape, w, 1.0 };
        return 1;
    }

    size_t fluorescence_models() const override { return m_shapes ? fluo::jung_shapes_len(**m_shapes) : 0; }

    const fluo::Fluorescence *fluorescence_model(size_t i) const override {
        return m_shapes ? &fluo::jung_fluorescence(shape(i)) : nullptr;
    }

    UnpolarizedSpectrum elastic_albedo(const SurfaceInteraction3f &si) const override {
        if constexpr (is_rgb_v<Spectrum>) {
            if (m_shapes) {
                Color3f e = textured_rgb_elastic(si, hit_params(si, true));
                return m_reflectance ? e : dr::clip(e, 0.f, 1.f);
            }
            if (!m_reflectance)
                return m_rgb_elastic_albedo;
            UnpolarizedSpectrum r = m_reflectance->eval(si, true);
            return m_modifies_reflectance ? r * m_rgb_elastic_scale : r;
        } else {
            return albedo(si, true);
        }
    }

    UnpolarizedSpectrum eval_elastic(const SurfaceInteraction3f &si, const Vector3f &wo) const override {
        Float cos_i = Frame3f::cos_theta(si.wi), cos_o = Frame3f::cos_theta(wo);
        if (!(cos_i > 0.f && cos_o > 0.f))
            return 0.f;
        return elastic_albedo(si) * dr::InvPi<Float> * cos_o;
    }

    std::string to_string() const override {
        std::ostringstream oss;
        oss << "FluoJung[" << std::endl
            << "  model = " << std::string(fluo::jung_to_string(**m_model)) << "," << std::endl;
        if (m_reflectance)
            oss << "  reflectance = " << string::indent(m_reflectance) << std::endl;
        for (size_t i = 0; i < NParams; ++i)
            if (m_param_tex[i])
                oss << "  " << ParamNames[i] << " = " << string::indent(m_param_tex[i]) << "," << std::endl;
        if (m_shapes)
            oss << "  dye shapes = " << fluo::jung_shapes_len(**m_shapes) << " ((emission_peak, stokes_shift) pairs),"
                << std::endl;
        if (m_color_mode)
            oss << "  color = " << m_color_text << "," << std::endl
                << "  cube = " << std::string(fluo::upsample_cube_describe(**m_cube)) << std::endl;
        oss << "]";
        return oss.str();
    }

    MI_DECLARE_CLASS(FluoJung)

private:
    /// Validate the configuration in Rust and precompute what each variant needs.
    void rebuild() {
        init_param_textures();
        m_model = fluo_detail::rust_call(Plugin, [&] { return fluo::jung_new(m_config); });
        m_build = fluo_detail::WavelengthMemo::next_build();
        m_emission_peak = (ScalarFloat) m_config.emission_peak;
        m_stokes_shift  = (ScalarFloat) m_config.stokes_shift;
        m_concentration = (ScalarFloat) m_config.concentration;
        m_quantum_yield = (ScalarFloat) m_config.quantum_yield;
        // c = 0 leaves the elastic part untouched: skip the Rust call per interaction.
        m_modifies_reflectance = m_config.concentration > 0.0;
        if constexpr (is_rgb_v<Spectrum>) {
            auto to_color = [](const fluo::Rgb &c) {
                return Color3f((ScalarFloat) c.r, (ScalarFloat) c.g, (ScalarFloat) c.b);
            };
            // Served albedo: elastic + reradiation, bounded to [0, 1] per channel
            // (fluo::rgb_bounded_albedo; a channel above 1 gains energy in a furnace).
            m_rgb_albedo = to_color(fluo::jung_rgb_albedo(**m_model));
            m_rgb_elastic_scale = to_color(fluo::jung_rgb_elastic_scale(**m_model));
            m_rgb_fluorescence = to_color(fluo::jung_rgb_fluorescence(**m_model));
            m_rgb_elastic_albedo = dr::clip(to_color(fluo::jung_rgb_elastic(**m_model)), 0.f, 1.f);
            m_shape_parts.clear();
            for (size_t i = 0; m_shapes && i < fluo::jung_shapes_len(**m_shapes); ++i)
                m_shape_parts.push_back(fluo::jung_rgb_parts(shape(i), **m_model));
        }
    }

    /// Textured parameters: read and validate every texture's values (per texel for a
    /// bitmap, constituent values otherwise), and build one dye shape per (λe, s) pair
    /// the textures can combine. m_config takes a representative value of each textured
    /// parameter, so that the base model (the sigmoid reflectance) stays valid.
    void init_param_textures() {
        std::optional<fluo_detail::JungShapeSet> set = fluo_detail::jung_shape_set(Plugin, m_param_tex, m_config);
        if (!set) {
            m_shapes.reset();
            return;
        }
        m_shapes_fluoresce = set->fluoresce;
        m_peak_levels = std::move(set->peaks);
        m_shift_levels = std::move(set->shifts);
        m_shapes = std::move(set->shapes);
    }

    /// A textured material's parameters at a hit: its dye shape, c and Q.
    struct Hit {
        size_t shape;
        float c, q;
    };

    /// Evaluate the parameter textures at si (Mitsuba's own lookup: to_uv, filtering).
    /// c and Q enter linearly and take the texture's value (clamped to [0, 1]: a
    /// filtered value lies between validated texels); λe and s select the nearest of
    /// the texture's validated values, so every shape the hit uses was built at load.
    Hit hit_params(const SurfaceInteraction3f &si, Mask active) const {
        auto unit = [&](size_t i) {
            if (!m_param_tex[i])
                return (float) (i == Conc ? m_config.concentration : m_config.quantum_yield);
            float v = m_param_tex[i]->eval_1(si, active);
            return std::isfinite(v) ? std::clamp(v, 0.f, 1.f) : 0.f;
        };
        size_t pi = m_param_tex[Peak] ? fluo_detail::nearest_level(m_peak_levels, m_param_tex[Peak]->eval_1(si, active)) : 0;
        size_t si_ = m_param_tex[Shift] ? fluo_detail::nearest_level(m_shift_levels, m_param_tex[Shift]->eval_1(si, active)) : 0;
        return { pi * m_shift_levels.size() + si_, unit(Conc), unit(Yield) };
    }

    const fluo::JungModel &shape(size_t i) const { return fluo::jung_shapes_model(**m_shapes, i); }

    /// RGB variant, textured parameters: the elastic albedo at a hit (unclamped).
    Color3f textured_rgb_elastic(const SurfaceInteraction3f &si, const Hit &h) const {
        const fluo::JungRgbParts &p = m_shape_parts[h.shape];
        auto color = [](const fluo::Rgb &c) { return Color3f((ScalarFloat) c.r, (ScalarFloat) c.g, (ScalarFloat) c.b); };
        if (m_reflectance) {
            Color3f r = m_reflectance->eval(si, true);
            return r * dr::clip(1.f - h.c * color(p.absorbed_scale), 0.f, 1.f);
        }
        return color(p.reflectance) - h.c * color(p.reflectance_absorbed);
    }

    /// `color`: load the cube, then look up a constant colour once or every texel of
    /// a (raw) bitmap texture once.
    void init_color(const Properties &props) {
        using namespace fluo_detail;
        JungColorOptions o = jung_color_options(Plugin, props);
        m_color_mode = true;
        const std::string &space = o.space, &cube_file = o.cube_file;
        m_lookup = o.lookup;
        m_use_fluorescence = o.fluorescence;
        m_texel_bilinear = o.bilinear;
        m_cube = rust_call(Plugin, [&] { return fluo::upsample_cube_load(space, cube_file); });
        if (props.type("color") == Properties::Type::Color) {
            ScalarColor3f c = props.get<ScalarColor3f>("color");
            std::array<double, 3> rgb = { (double) c[0], (double) c[1], (double) c[2] };
            m_color_text = tfm::format("(%g, %g, %g) %s", rgb[0], rgb[1], rgb[2], space);
            m_config = rust_call(Plugin, [&] {
                return fluo::upsample_lookup(**m_cube, rust::Slice<const double>(rgb.data(), 3), m_lookup,
                                             m_use_fluorescence);
            });
            return;
        }
        ref<Texture> tex = props.get_texture<Texture>("color"); // jung_color_options checked the type
        if (!tex->is_spatially_varying())
            Throw("%s: \"color\" is a constant texture; give it as <rgb name=\"color\" value=\"r, g, b\"/> "
                  "(or as a raw bitmap texture)", Plugin);
        ScalarVector2i res = tex->resolution();
        if (!(res.x() > 0 && res.y() > 0))
            Throw("%s: \"color\" texture has no texels", Plugin);
        std::vector<float> texels((size_t) res.x() * (size_t) res.y() * 3);
        SurfaceInteraction3f si = dr::zeros<SurfaceInteraction3f>();
        try {
            for (int y = 0; y < res.y(); ++y)
                for (int x = 0; x < res.x(); ++x) {
                    si.uv = Point2f((x + .5f) / res.x(), (y + .5f) / res.y());
                    Color3f v = tex->eval_3(si, true);
                    size_t o = 3 * ((size_t) y * res.x() + x);
                    texels[o] = v[0]; texels[o + 1] = v[1]; texels[o + 2] = v[2];
                }
        } catch (const std::exception &e) {
            Throw("%s: cannot read the \"color\" texture's RGB texels (it must be a 3-channel "
                  "bitmap with <boolean name=\"raw\" value=\"true\"/>, holding linear %s): %s",
                  Plugin, space, e.what());
        }
        m_texture_res = res;
        m_color_text = tfm::format("texture %d x %d %s", res.x(), res.y(), space);
        m_texture_models = rust_call(Plugin, [&] {
            return fluo::jung_texture_new(**m_cube, (size_t) res.x(), (size_t) res.y(),
                                          rust::Slice<const float>(texels.data(), texels.size()),
                                          m_lookup, m_use_fluorescence);
        });
        m_color_text += tfm::format(", %zu distinct coefficient sets, %s texels",
                                    fluo::jung_texture_distinct(**m_texture_models),
                                    m_texel_bilinear ? "bilinear" : "nearest");
    }

    /// texel_interpolation = bilinear: the (up to) four texels around si.uv (texel
    /// centres, repeat wrap) with their bilinear weights (Jung et al. 2019, Fig. 12:
    /// interpolate the texels' reradiation, not their coefficients).
    struct Texels {
        size_t n = 0;
        int64_t x[4]{}, y[4]{};
        double w[4]{};
    };
    Texels texels_at(const SurfaceInteraction3f &si) const {
        Texels t;
        if (!m_texel_bilinear) {
            auto [x, y] = texel_of(si);
            t.n = 1;
            t.x[0] = x;
            t.y[0] = y;
            t.w[0] = 1.0;
            return t;
        }
        double u = (double) si.uv.x() * m_texture_res.x() - 0.5, v = (double) si.uv.y() * m_texture_res.y() - 0.5;
        if (!std::isfinite(u) || !std::isfinite(v))
            u = v = 0.0;
        double fu = std::floor(u), fv = std::floor(v), tu = u - fu, tv = v - fv;
        for (int a = 0; a < 2; ++a)
            for (int b = 0; b < 2; ++b) {
                double w = (a ? tu : 1.0 - tu) * (b ? tv : 1.0 - tv);
                if (!(w > 0.0))
                    continue;
                t.x[t.n] = (int64_t) fu + a;
                t.y[t.n] = (int64_t) fv + b;
                t.w[t.n++] = w;
            }
        return t;
    }

    /// Nearest texel (repeat wrap) of the colour texture at si.uv.
    std::pair<int64_t, int64_t> texel_of(const SurfaceInteraction3f &si) const {
        return { (int64_t) dr::floor(si.uv.x() * m_texture_res.x()),
                 (int64_t) dr::floor(si.uv.y() * m_texture_res.y()) };
    }

    const fluo::JungModel &texel_model(const SurfaceInteraction3f &si) const {
        auto [x, y] = texel_of(si);
        return fluo::jung_texture_model(**m_texture_models, x, y);
    }

    /// Directional-hemispherical albedo served to Mitsuba (see the doc comment).
    UnpolarizedSpectrum albedo(const SurfaceInteraction3f &si, Mask active) const {
        if (m_shapes) {
            Hit h = hit_params(si, active);
            if constexpr (is_rgb_v<Spectrum>) {
                Color3f e = textured_rgb_elastic(si, h);
                if (!(h.c > 0.f && h.q > 0.f))
                    return m_reflectance ? e : dr::clip(e, 0.f, 1.f);
                const fluo::JungRgbParts &p = m_shape_parts[h.shape];
                double w = (double) h.c * (double) h.q;
                fluo::Rgb b = fluo::rgb_bounded_albedo(fluo::Rgb{ e[0], e[1], e[2] },
                                                       fluo::Rgb{ w * p.fluorescence.r, w * p.fluorescence.g,
                                                                  w * p.fluorescence.b });
                return Color3f((ScalarFloat) b.r, (ScalarFloat) b.g, (ScalarFloat) b.b);
            } else {
                std::array<float, 4> lambda = fluo_detail::wavelengths_of(si.wavelengths), a{}, r{};
                fluo::jung_absorption(shape(h.shape), fluo_detail::slice(lambda), fluo_detail::slice_mut(a));
                UnpolarizedSpectrum refl;
                if (m_reflectance) {
                    refl = m_reflectance->eval(si, active);
                } else {
                    fluo::jung_reflectance(**m_model, fluo_detail::slice(lambda), fluo_detail::slice_mut(r));
                    refl = UnpolarizedSpectrum(r[0], r[1], r[2], r[3]);
                }
                return refl * (1.f - h.c * UnpolarizedSpectrum(a[0], a[1], a[2], a[3]));
            }
        }
        if (m_texture_models) {
            // the texel's value, or the bilinear mixture of the four around si
            Texels t = texels_at(si);
            UnpolarizedSpectrum sum(0.f);
            for (size_t i = 0; i < t.n; ++i) {
                if constexpr (is_rgb_v<Spectrum>) {
                    fluo::Rgb c = fluo::jung_texture_rgb(**m_texture_models, t.x[i], t.y[i]);
                    sum += (float) t.w[i] * Color3f((ScalarFloat) c.r, (ScalarFloat) c.g, (ScalarFloat) c.b);
                } else {
                    std::array<float, 4> lambda = fluo_detail::wavelengths_of(si.wavelengths), out{};
                    fluo::jung_elastic_albedo(fluo::jung_texture_model(**m_texture_models, t.x[i], t.y[i]),
                                              fluo_detail::slice(lambda), fluo_detail::slice_mut(out));
                    sum += (float) t.w[i] * UnpolarizedSpectrum(out[0], out[1], out[2], out[3]);
                }
            }
            return sum;
        }
        if constexpr (is_rgb_v<Spectrum>) {
            if (!m_reflectance)
                return m_rgb_albedo;
            UnpolarizedSpectrum r = m_reflectance->eval(si, active);
            if (!m_modifies_reflectance)
                return r;
            Color3f e = r * m_rgb_elastic_scale;
            fluo::Rgb b = fluo::rgb_bounded_albedo(fluo::Rgb{ e[0], e[1], e[2] },
                                                   fluo::Rgb{ m_rgb_fluorescence[0], m_rgb_fluorescence[1],
                                                              m_rgb_fluorescence[2] });
            return Color3f((ScalarFloat) b.r, (ScalarFloat) b.g, (ScalarFloat) b.b);
        } else {
            std::array<float, 4> lambda = fluo_detail::wavelengths_of(si.wavelengths);
            if (!m_reflectance) {
                const std::array<float, 4> &out = fluo_detail::WavelengthMemo::get(m_build, lambda, [&](std::array<float, 4> &v) {
                    fluo::jung_elastic_albedo(**m_model, fluo_detail::slice(lambda), fluo_detail::slice_mut(v));
                });
                return UnpolarizedSpectrum(out[0], out[1], out[2], out[3]);
            }
            UnpolarizedSpectrum r = m_reflectance->eval(si, active);
            if (!m_modifies_reflectance)
                return r;
            const std::array<float, 4> &out = fluo_detail::WavelengthMemo::get(m_build, lambda, [&](std::array<float, 4> &v) {
                fluo::jung_elastic_factor(**m_model, fluo_detail::slice(lambda), fluo_detail::slice_mut(v));
            });
            return r * UnpolarizedSpectrum(out[0], out[1], out[2], out[3]);
        }
    }

    /// The numeric parameters that take a texture, in the order of m_param_tex.
    enum Param { Peak = fluo_detail::JungPeak, Shift, Conc, Yield, NParams };
    static constexpr const char *const *ParamNames = fluo_detail::JungParamNames;

    fluo::JungConfig m_config = fluo::jung_default_config(); ///< the defaults live in Rust (JungParams)
    std::optional<rust::Box<fluo::JungModel>> m_model; ///< set by rebuild() in the constructor
    /// This model's key in the per-thread memo of its elastic albedo/factor: a vertex
    /// asks for it up to three times (eval_pdf, sample, fluo_path's elastic/shift
    /// choice), and a path keeps its wavelengths until a shift.
    uint64_t m_build = 0;
    ref<Texture> m_reflectance;
    ScalarFloat m_emission_peak = 0.f, m_stokes_shift = 0.f, m_concentration = 0.f,
                m_quantum_yield = 0.f;
    bool m_modifies_reflectance = false;
    // `color` (wide-gamut upsampling through a coefficient cube)
    bool m_color_mode = false, m_use_fluorescence = true;
    bool m_texel_bilinear = false; ///< texel_interpolation = bilinear
    std::string m_lookup, m_color_text;
    std::optional<rust::Box<fluo::UpsampleCube>> m_cube;
    std::optional<rust::Box<fluo::JungTexture>> m_texture_models; ///< per-texel models
    ScalarVector2i m_texture_res = ScalarVector2i(0, 0);
    // textured numeric parameters (null: the float in m_config)
    ref<Texture> m_param_tex[NParams];
    std::vector<float> m_peak_levels, m_shift_levels; ///< the validated values of λe and s
    std::optional<rust::Box<fluo::JungShapes>> m_shapes; ///< one dye shape per (λe, s) pair
    bool m_shapes_fluoresce = false; ///< some texel has c > 0 and some Q > 0
    std::vector<fluo::JungRgbParts> m_shape_parts; ///< RGB variant: per dye shape
    Color3f m_rgb_albedo = 0.f, m_rgb_elastic_scale = 1.f, m_rgb_fluorescence = 0.f,
            m_rgb_elastic_albedo = 0.f;
};

static const bool fluo_jung_registered =
    (fluo_detail::register_scalar_plugin<FluoJung>("fluo_jung", ObjectType::BSDF), true);

NAMESPACE_END(mitsuba)
