// Transforms given as text by users (REST bodies, command-line flags).
#pragma once

#include <optional>
#include <vector>

#include "common/geometry.hpp"

namespace stereomap::common {

// A transform from the 7 numbers tx ty tz qx qy qz qw (TUM order); nullopt unless there are
// 7, all finite, with a unit quaternion.
std::optional<Rigid3> rigidFromTxyzQxyzw(const std::vector<double>& values);

}  // namespace stereomap::common
