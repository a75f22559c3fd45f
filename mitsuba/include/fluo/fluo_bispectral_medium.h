// What every fluorescent participating medium shares (fluo_qd_medium, fluo_dye_medium;
// their interface to fluo_volpath is BispectralMedium in fluo_medium.h): whether
// fluo_volpath transports its fluorescence this render, and the once-per-scene warning
// when no integrator does. Re-emission is isotropic.
#pragma once

#include <array>
#include <atomic>
#include <cmath>

#include <mitsuba/core/logger.h>
#include <mitsuba/render/interaction.h>

#include "fluo-mitsuba/src/bridge.rs.h"

NAMESPACE_BEGIN(mitsuba)

namespace fluo_detail {
/// Isotropic re-emission, 1/(4π) per steradian (fluo_volpath, every variant).
constexpr float InvFourPi = (float) (0.25 * M_1_PI);

/// Armed when a fluorescent medium is constructed, disarmed by the first warning:
/// one "needs fluo_volpath" warning per loaded scene.
inline std::atomic<bool> &unmanaged_medium_warning_armed() {
    static std::atomic<bool> armed{ true };
    return armed;
}

} // namespace fluo_detail

/// What every fluorescent medium shares in every variant: whether fluo_volpath transports
/// its fluorescence this render, and the once-per-scene warning when no integrator does.
class ManagedMedium {
public:
    ManagedMedium() { fluo_detail::unmanaged_medium_warning_armed().store(true, std::memory_order_relaxed); }
    virtual ~ManagedMedium() = default;

    /// fluo_volpath marks the media it transports when it prepares a render; any other
    /// integrator renders absorption without re-emission and says so once per scene.
    void set_managed(bool managed) const { m_managed.store(managed, std::memory_order_relaxed); }

protected:
    /// Warn (once per scene) when `fluorescent` and no fluo_volpath manages the medium.
    void warn_if_unmanaged(const char *plugin, bool fluorescent) const {
        if (m_managed.load(std::memory_order_relaxed) || !fluorescent)
            return;
        if (fluo_detail::unmanaged_medium_warning_armed().exchange(false, std::memory_order_relaxed)) {
            constexpr const char *ClassName = "fluo";
            Log(Warn, "%s: this medium fluoresces, but the scene's integrator does not transport "
                      "fluorescence in media: it absorbs without re-emitting. Use "
                      "<integrator type=\"fluo_volpath\"/> to render its fluorescence. (This warning is printed once per scene.)",
                plugin);
        }
    }

private:
    mutable std::atomic<bool> m_managed{ false };
};

NAMESPACE_END(mitsuba)
