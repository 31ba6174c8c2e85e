// A point cloud in one frame (named by the owner), with optional per-point intensity.
#pragma once

#include <cstdint>
#include <vector>

#include "common/geometry.hpp"

namespace stereomap::common {

struct PointCloud {
  std::vector<Vec3f> points;
  std::vector<uint8_t> intensity;  // empty, or one grey value per point

  size_t size() const { return points.size(); }
  bool hasIntensity() const { return !intensity.empty(); }
};

}  // namespace stereomap::common
