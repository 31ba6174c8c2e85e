// The sim flight the odometry's figures use (tests and stereomap-bench-vo): 300 frames at
// 10 Hz through a seeded room, with image noise (sigma 2 grey levels) and blur (sigma 1 px).
#pragma once

#include "onboard/sim/sim_source.hpp"

namespace stereomap::testing {

inline sim::SimSourceOptions noisyFlight(uint32_t seed) {
  sim::SimSourceOptions options{.seed = seed, .rate_hz = 10.0, .max_frames = 300};
  options.render.camera.noise_sigma = 2.0;
  options.render.camera.blur_sigma = 1.0;
  return options;
}

}  // namespace stereomap::testing
