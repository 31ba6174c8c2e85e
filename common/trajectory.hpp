// Trajectories on disk: TUM ("t tx ty tz qx qy qz qw", '#' comments) and KITTI (12 numbers
// per line, row-major 3x4 pose; time is the line index unless times are given). Errors name
// the file and the line.
#pragma once

#include <filesystem>
#include <string>
#include <vector>

#include "common/geometry.hpp"
#include "common/result.hpp"

namespace stereomap::common {

struct StampedPose {
  double t = 0;  // seconds
  Rigid3 pose;   // T_world_body (or camera), as the file has it
};
using Trajectory = std::vector<StampedPose>;

enum class TrajectoryFormat { kTum, kKitti };

// Reads either format; `format` nullptr: by the first data line (8 numbers: TUM, 12: KITTI).
// `kitti_times` (may be empty): a KITTI times.txt giving each line's stamp.
Result<Trajectory> readTrajectory(const std::filesystem::path& path,
                                  const std::filesystem::path& kitti_times = {},
                                  TrajectoryFormat* format = nullptr);

std::string tumText(const Trajectory& trajectory);
std::string kittiText(const Trajectory& trajectory);
// Writes the whole file atomically (common::writeFileAtomically); fails naming the file.
Status writeText(const std::filesystem::path& path, const std::string& text);

}  // namespace stereomap::common
