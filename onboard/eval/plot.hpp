// A picture of an evaluation for people: the trajectories from above (reference and aligned
// estimate, on the two axes along which the reference spreads most) and the position error
// over time.
#pragma once

#include <string>
#include <vector>

#include "common/trajectory.hpp"

namespace stereomap::eval {

// PNG bytes (1400 x 600). `errors` has one value per pose pair. `frames`: the stamps are
// frame numbers (KITTI files without times), not seconds.
std::string plotPng(const common::Trajectory& ref, const common::Trajectory& aligned_est,
                    const std::vector<double>& errors, const std::string& title,
                    bool frames = false);

}  // namespace stereomap::eval
