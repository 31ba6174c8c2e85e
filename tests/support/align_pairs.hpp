// Pairs of maps of one place, each in its own frame, with the true transform between them:
// for align_test and stereomap-bench-align, so that both count alike.
//   flyRoom:  a simulated room flown along a scripted path, mapped from exact ray casts in a
//             frame of the caller's choosing (a vehicle's odometry origin);
//   cutPair:  two overlapping boxes cut from one map (a real OctoMap file), the second moved
//             into a frame of its own and re-voxelised there;
//   corridor: a long corridor, plain or with pillars at a fixed pitch (a repeated pattern).
#pragma once

#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "common/geometry.hpp"
#include "common/point_cloud.hpp"
#include "onboard/sim/flight.hpp"
#include "onboard/sim/scene.hpp"
#include "server/fusion/occupancy_map.hpp"

namespace stereomap::testing {

struct MapPair {
  std::unique_ptr<fusion::OccupancyMap> a, b;
  common::Rigid3 T_a_b;  // the truth: x_a = T_a_b x_b
};

// The scene mapped along `flight` from t0 to t1 (s), seen through a 90 x 70 degree camera
// (80 x 60 rays, 8 m range, 4 frames per second), in the frame `T_own_world`.
std::unique_ptr<fusion::OccupancyMap> flyRoom(const sim::Scene& scene,
                                              const sim::FlightOptions& flight, double t0,
                                              double t1, const common::Rigid3& T_own_world,
                                              double resolution);

// Occupied and free voxels of `whole` inside each box; A keeps the map's frame, B's voxels
// are moved by T_b_world (occupied ones sampled at 8 points each, so that a rotated grid
// leaves no holes; free space sampled at most 8 per axis per pruned block).
MapPair cutPair(const fusion::OccupancyMap& whole, const common::Box3& box_a,
                const common::Box3& box_b, const common::Rigid3& T_b_world);

// A real drive's frames as the vehicle maps them: each frame's cloud (the onboard depth step,
// default options for `resolution`) and the left camera's true pose.
struct Drive {
  std::vector<common::PointCloud> clouds;
  std::vector<common::Rigid3> T_world_camera;
  double max_range_m = 0;
};
// The source `spec` ("kitti:DIR"), read to its end; nullopt when it cannot be opened or has
// no ground truth.
std::optional<Drive> readDrive(const std::string& spec, double resolution);

// Frames [0, first_end) and [second_begin, end) of the drive, each fused in the frame of its
// own first camera pose (moved further by `T_extra` for the second), at `resolution`.
MapPair drivePair(const Drive& drive, size_t first_end, size_t second_begin,
                  const common::Rigid3& T_extra, double resolution);

// Two windows of `whole`, `width` metres square over its whole height, centred `offset` from
// the middle of its occupied bounds and overlapping by `share` of the width along x; the
// second moved by T_b_world (cutPair).
MapPair windowPair(const fusion::OccupancyMap& whole, double width, double share,
                   const common::Rigid3& T_b_world, const common::Vec3& offset = {0, 0, 0});

// A map made of the given voxel centres (occupied wins over free where both fall).
std::unique_ptr<fusion::OccupancyMap> mapOfPoints(double resolution,
                                                  const std::vector<common::Vec3>& occupied,
                                                  const std::vector<common::Vec3>& free);

// The part x0..x1 of an endless corridor along x, 2.4 m wide and 3 m high (floor, walls, the
// free space inside; no ends, no ceiling), with 0.4 m pillars every `pitch` metres along one
// wall when pitch > 0 (a repeated pattern), in the frame T_own_world.
std::unique_ptr<fusion::OccupancyMap> corridorMap(double x0, double x1, double pitch,
                                                  const common::Rigid3& T_own_world,
                                                  double resolution);

// A pose with yaw `yaw_deg`, small roll and pitch, and translation t.
common::Rigid3 poseOf(double yaw_deg, const common::Vec3& t, double roll_deg = 0,
                      double pitch_deg = 0);

// Translation (m) and rotation (deg) error of `estimate` against `truth`.
struct PoseError {
  double translation_m = 0, rotation_deg = 0;
};
PoseError poseError(const common::Rigid3& estimate, const common::Rigid3& truth);

}  // namespace stereomap::testing
