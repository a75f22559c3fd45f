// The Lambertian lobe shared by fluo's diffuse materials (fluo_jung, fluo_matrix,
// fluo_gmm): cosine-weighted sampling, f = albedo / π, front side only, exactly as
// Mitsuba's `diffuse`. Each BSDF method of a plugin calls the matching function here
// with a callable returning its albedo at si (evaluated only where the lobe is non-zero).
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
        if (!active || !ctx.is_enabled(BSDFFlags::DiffuseReflection))
            return { bs, 0.f };
        bs.wo = warp::square_to_cosine_hemisphere(sample2);
        bs.pdf = warp::square_to_cosine_hemisphere_pdf(bs.wo);
        bs.eta = 1.f;
        bs.sampled_type = +BSDFFlags::DiffuseReflection;
        bs.sampled_component = 0;
        if (!(bs.pdf > 0.f))
            return { bs, 0.f };
        return { bs, depolarizer<Spectrum>(albedo()) };
    }

    /// Whether the lobe is non-zero for (si.wi, wo).
    static bool active_for(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
                           Mask active) {
        active &= Frame3f::cos_theta(si.wi) > 0.f && Frame3f::cos_theta(wo) > 0.f;
        return active && ctx.is_enabled(BSDFFlags::DiffuseReflection);
    }

    template <typename Albedo>
    static Spectrum eval(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo,
                         Mask active, Albedo &&albedo) {
        if (!active_for(ctx, si, wo, active))
            return 0.f;
        return depolarizer<Spectrum>(albedo() * dr::InvPi<Float> * Frame3f::cos_theta(wo));
    }

    static Float pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si, const Vector3f &wo, Mask active) {
        if (!active_for(ctx, si, wo, active))
            return 0.f;
        return warp::square_to_cosine_hemisphere_pdf(wo);
    }

    template <typename Albedo>
    static std::pair<Spectrum, Float> eval_pdf(const BSDFContext &ctx, const SurfaceInteraction3f &si,
                                               const Vector3f &wo, Mask active, Albedo &&albedo) {
        if (!active_for(ctx, si, wo, active))
            return { 0.f, 0.f };
        return { depolarizer<Spectrum>(albedo() * dr::InvPi<Float> * Frame3f::cos_theta(wo)),
                 warp::square_to_cosine_hemisphere_pdf(wo) };
    }
};

NAMESPACE_END(mitsuba)
