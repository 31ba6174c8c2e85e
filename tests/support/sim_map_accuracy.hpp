// How right a map of a simulated room is, made in process: the onboard depth step (matcher
// and cloud) on the sim's images under a camera model, fused at a resolution with the
// ground-truth poses, compared with the room's exact geometry. Shared by
// fusion_accuracy_test and stereomap-bench-map so that both count alike:
//   precision: share of the occupied voxels a true surface passes through;
//   recall:    share of the true surface voxels the stereo camera saw (in both images, depth
//              within range) that are occupied; a point on a voxel face belongs to the
//              voxels on both sides, as precision counts them;
//   free:      share of samples on the true camera rays, at least two voxels before the
//              surface, that the map classifies free.
#pragma once

#include <cstdint>
#include <functional>
#include <optional>

#include "onboard/sim/renderer.hpp"
#include "onboard/stereo/depth_step.hpp"
#include "server/fusion/occupancy_map.hpp"

namespace stereomap::testing {

struct SimMapSetup {
  uint32_t room = 1;  // the room's seed
  int frames = 60;    // of the scripted flight at 10 Hz
  sim::CameraModel camera = sim::CameraModel::clean();
  // The vehicle's depth step (on the true poses here; the vehicle uses its odometry's).
  stereo::DepthOptions depth;
  // True surface points up to this depth count for recall, whatever the cloud's range (the
  // vehicle's default range).
  double seen_range_m = 6.0;
  fusion::OccupancyMap::Options map = fusion::OccupancyMap::Options::octomapPreset(0.05);
  // What of each frame's cloud reaches the map (a radio link in between, say): may change the
  // cloud (in the camera frame); false: the frame's cloud is not fused. Unset: every cloud.
  std::function<bool(common::PointCloud& cloud, const common::Rigid3& T_map_camera,
                     int64_t stamp_ns)>
      send;
};

struct SimMapAccuracy {
  double precision = 0, recall = 0, free_space = 0;
  // Share of the occupied voxels within one and within two voxels of a true surface.
  double precision_1 = 0, precision_2 = 0;
  size_t occupied = 0, seen = 0, free_samples = 0;
  double depth_ms = 0;     // median of the onboard depth step (disparity and cloud) per frame
  double noise_sigma = 0;  // the depth step's last image noise estimate, grey levels
  int level = -1;          // the noise level it chose at the end (-1: clean images)
};

SimMapAccuracy measureSimMap(const SimMapSetup& setup);

}  // namespace stereomap::testing
