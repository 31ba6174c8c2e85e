// Poses as the messages carry them (PoseMsg, CloudFrameMsg's sensor, keyframes, landing
// targets): a position array x y z and an orientation array x y z w. One place converts
// them to and from common::Rigid3, so that the quaternion's order is written once.
#pragma once

#include <array>

#include "common/geometry.hpp"

namespace stereomap::proto {

// The orientation as sent (not normalised: validation checks its norm first).
inline common::Quat quatFromFields(const std::array<double, 4>& orientation) {
  return common::Quat(orientation[3], orientation[0], orientation[1], orientation[2]);
}

// The pose, its rotation normalised.
inline common::Rigid3 rigidFromFields(const std::array<double, 3>& position,
                                      const std::array<double, 4>& orientation) {
  return {quatFromFields(orientation).normalized(),
          common::Vec3(position[0], position[1], position[2])};
}

// Writes `T` (its rotation normalised) into a message's arrays.
inline void fieldsFromRigid(const common::Rigid3& T, std::array<double, 3>& position,
                            std::array<double, 4>& orientation) {
  const common::Quat q = T.rotation.normalized();
  position = {T.translation.x(), T.translation.y(), T.translation.z()};
  orientation = {q.x(), q.y(), q.z(), q.w()};
}

}  // namespace stereomap::proto
