// The Lambertian lobe shared by fluo's diffuse materials (fluo_jung, fluo_matrix,
// fluo_gmm): cosine-weighted sampling, f = albedo / π, front side only, exactly as
// Mitsuba's `diffuse`. Each BSDF method of a plugin calls the matching function here
// with a callable returning its albedo at si (evaluated only where the lobe is non-zero; in
// the JIT variants, masked per lane).
#pragma once

#include <mitsuba/core/warp.h>
#include <mitsuba/render/bsdf.h>

NAMESPACE_BEGIN(mitsuba)

template <typename Float, typename Spectrum> struct Lambertian {
    MI_IMPORT_TYPES()

    template <typename Albedo>
    static std::pair<BSDFSample3f, Spectrum> sample(const BSDFContext &ctx, const SurfaceInteraction3f &si,
                                                    const Point2f &sample2, Mask active, Albedo &&albedo) {
        BSDFSample3f bs = dr::zeros<BSDFSample3f>();
        active &= Frame3f::cos_theta(si.wi) > 0.f;
        if (dr::none_or<false>(active) || !ctx.is_enabled(BSDFFlags::DiffuseReflection))
            return { bs, 0.f };
        bs.wo = warp::square_to_cosine_hemisphere(sample2);
        bs.pdf = warp::square_to_cosine_hemisphere_pdf(bs.wo);
        bs.eta = 1.f;
        bs.sampled_type = +BSDFFlags::DiffuseReflection;
        bs.sampled_component = 0;
        if constexpr (dr::is_jit_v<Float>) {
            active &= bs.pdf > 0.f;
            bs.pdf = dr::select(active, bs.pdf, 0.f);
            return { bs, depolarizer<Spectrum>(albedo()) & active };
        } else {
            if (!(bs.pdf > 0.f))
                return { bs, 0.f };
            return { bs, depolarizer<Spectrum>(albedo()) };
        }
    }

    /// Where the lobe is non-zero for (si.wi, wo).
    static Mask active_for(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
                           Mask active) {
        active &= Frame3f::cos_theta(si.wi) > 0.f && Frame3f::cos_theta(wo) > 0.f;
        return active && ctx.is_enabled(BSDFFlags::DiffuseReflection);
    }

    template <typename Albedo>
    static Spectrum eval(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
                         Mask active, Albedo &&albedo) {
        return eval_pdf(ctx, si, wo, active, albedo).first;
    }

    static Float pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo, Mask active) {
        Mask on = active_for(ctx, si, wo, active);
        return dr::none_or<false>(on) ? Float(0.f) : dr::select(on, warp::square_to_cosine_hemisphere_pdf(wo), 0.f);
    }

    template <typename Albedo>
    static std::pair<Spectrum, Float> eval_pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si,
                                               const Vector3f &wo, Mask active, Albedo &&albedo) {
        Mask on = active_for(ctx, si, wo, active);
        if (dr::none_or<false>(on))
            return { 0.f, 0.f };
        return { depolarizer<Spectrum>(albedo() * dr::InvPi<Float> * Frame3f::cos_theta(wo)) & on,
                 dr::select(on, warp::square_to_cosine_hemisphere_pdf(wo), 0.f) };
    }
};

/// The BSDF methods (sample, eval, pdf, eval_pdf, eval_diffuse_reflectance) of a plugin
/// whose lobe is Lambertian, in its class body: `ALBEDO` is an expression of `si` and
/// `active` giving the albedo, `BEFORE_SAMPLE` a statement sample() runs first (e.g. the
/// unmanaged-use warning; `(void) 0` for none). And BispectralBSDF::jit_lambertian_elastic: the
/// plugin's jit_choose hands back ALBEDO at λo (spectral), for fluo_path to evaluate this
/// lobe with.
#define FLUO_LAMBERTIAN_BSDF_METHODS(ALBEDO, BEFORE_SAMPLE)                                                   \
    std::pair<BSDFSample3f, Spectrum> sample(const BSDFContext &ctx, const SurfaceInteraction3f &si,          \
                                             Float /* sample1 */, const Point2f &sample2, Mask active)        \
        const override {                                                                                      \
        BEFORE_SAMPLE;                                                                                        \
        return Lambertian<Float, Spectrum>::sample(ctx, si, sample2, active, [&] { return ALBEDO; });         \
    }                                                                                                         \
    Spectrum eval(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo, Mask active)    \
        const override {                                                                                      \
        return Lambertian<Float, Spectrum>::eval(ctx, si, wo, active, [&] { return ALBEDO; });                \
    }                                                                                                         \
    Float pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo, Mask active)        \
        const override {                                                                                      \
        return Lambertian<Float, Spectrum>::pdf(ctx, si, wo, active);                                         \
    }                                                                                                         \
    std::pair<Spectrum, Float> eval_pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si,               \
                                        const Vector3f &wo, Mask active) const override {                     \
        return Lambertian<Float, Spectrum>::eval_pdf(ctx, si, wo, active, [&] { return ALBEDO; });            \
    }                                                                                                         \
    /* (the albedo once for both: Mitsuba's default evaluates it in eval_pdf and in sample) */                \
    std::tuple<Spectrum, Float, BSDFSample3f, Spectrum> eval_pdf_sample(                                     \
        const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo, Float /* sample1 */,     \
        const Point2f &sample2, Mask active) const override {                                                \
        BEFORE_SAMPLE;                                                                                        \
        auto a = ALBEDO;                                                                                      \
        auto [val, pdf] = Lambertian<Float, Spectrum>::eval_pdf(ctx, si, wo, active, [&] { return a; });       \
        auto [bs, weight] = Lambertian<Float, Spectrum>::sample(ctx, si, sample2, active, [&] { return a; });  \
        return { val, pdf, bs, weight };                                                                      \
    }                                                                                                         \
    Spectrum eval_diffuse_reflectance(const SurfaceInteraction3f &si, Mask active) const override {           \
        (void) active;                                                                                        \
        return depolarizer<Spectrum>(ALBEDO);                                                                 \
    }                                                                                                         \
    bool jit_lambertian_elastic() const override { return true; }

NAMESPACE_END(mitsuba)
