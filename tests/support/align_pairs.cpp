#include "tests/support/align_pairs.hpp"

#include <octomap/OcTree.h>

#include "onboard/sources/source_registry.hpp"
#include "onboard/stereo/depth_step.hpp"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

namespace stereomap::testing {

using common::Rigid3;
using common::Vec3;
using fusion::OccupancyMap;

std::unique_ptr<OccupancyMap> flyRoom(const sim::Scene& scene, const sim::FlightOptions& options,
                                      double t0, double t1, const Rigid3& T_own_world,
                                      double resolution) {
  auto map = std::make_unique<OccupancyMap>(OccupancyMap::Options::octomapPreset(resolution));
  const sim::Flight flight(options);
  constexpr int kCols = 80, kRows = 60;
  constexpr double kRange = 8.0;
  const double tan_x = std::tan(45.0 * M_PI / 180), tan_y = std::tan(35.0 * M_PI / 180);
  for (double t = t0; t <= t1 + 1e-9; t += 0.25) {
    const Rigid3 T_world_camera = flight.T_map_camera(t);
    common::PointCloud cloud;
    for (int r = 0; r < kRows; ++r) {
      for (int c = 0; c < kCols; ++c) {
        // OpenCV camera axes: x right, y down, z forward.
        const Vec3 ray_camera(tan_x * (2.0 * (c + 0.5) / kCols - 1),
                              tan_y * (2.0 * (r + 0.5) / kRows - 1), 1.0);
        const Vec3 ray_world = T_world_camera.rotation * ray_camera;
        const auto hit = scene.intersect(T_world_camera.translation, ray_world, kRange);
        if (!hit || (ray_camera * hit->t).norm() > kRange) continue;
        cloud.points.push_back((ray_camera * hit->t).cast<float>());
      }
    }
    map->insertCloud(cloud, T_own_world * T_world_camera, kRange);
  }
  return map;
}

std::unique_ptr<OccupancyMap> mapOfPoints(double resolution, const std::vector<Vec3>& occupied,
                                          const std::vector<Vec3>& free) {
  octomap::OcTree tree(resolution);
  const auto point = [](const Vec3& p) {
    return octomap::point3d(static_cast<float>(p.x()), static_cast<float>(p.y()),
                            static_cast<float>(p.z()));
  };
  for (const auto& p : free) tree.setNodeValue(point(p), tree.getClampingThresMinLog(), true);
  for (const auto& p : occupied) tree.setNodeValue(point(p), tree.getClampingThresMaxLog(), true);
  tree.updateInnerOccupancy();
  std::stringstream bytes;
  tree.writeBinary(bytes);
  auto map = OccupancyMap::load(bytes);
  if (!map) throw std::runtime_error("mapOfPoints: " + map.error().message);
  return std::move(map).value();
}

MapPair cutPair(const OccupancyMap& whole, const common::Box3& box_a, const common::Box3& box_b,
                const Rigid3& T_b_world) {
  const double v = whole.resolution();
  MapPair pair;
  pair.T_a_b = T_b_world.inverse();
  const auto cut = [&](const common::Box3& box, const Rigid3* T) {
    std::vector<Vec3> occupied, free;
    whole.visitKnown(box, [&](const Vec3& min_corner, double edge, fusion::Occupancy occupancy) {
      const int n = static_cast<int>(std::lround(edge / v));
      const int stride = occupancy == fusion::Occupancy::kFree ? std::max(1, n / 8) : 1;
      for (int i = 0; i < n; i += stride) {
        for (int j = 0; j < n; j += stride) {
          for (int k = 0; k < n; k += stride) {
            const Vec3 centre = min_corner + Vec3(i + 0.5, j + 0.5, k + 0.5) * v;
            if (!box.contains(centre)) continue;
            if (occupancy == fusion::Occupancy::kFree) {
              free.push_back(T ? *T * centre : centre);
            } else if (!T) {
              occupied.push_back(centre);
            } else {
              for (int s = 0; s < 8; ++s) {  // a rotated grid: no holes
                const Vec3 offset((s & 1 ? 0.25 : -0.25), (s & 2 ? 0.25 : -0.25),
                                  (s & 4 ? 0.25 : -0.25));
                occupied.push_back(*T * (centre + offset * v));
              }
            }
          }
        }
      }
    });
    return mapOfPoints(v, occupied, free);
  };
  pair.a = cut(box_a, nullptr);
  pair.b = cut(box_b, &T_b_world);
  return pair;
}

std::optional<Drive> readDrive(const std::string& spec, double resolution) {
  auto opened = sources::openSource(spec, {});
  if (!opened) return std::nullopt;
  auto& source = *opened->source;
  stereo::DepthOptions options;
  options.range = stereo::AutoRange{.map_resolution_m = resolution};
  stereo::DepthStep depth(source.camera(), options);
  Drive drive;
  while (auto frame = source.next()) {
    if (!frame->T_map_body) return std::nullopt;
    const Rigid3 T_world_camera = frame->T_map_camera_truth();
    drive.clouds.push_back(
        depth.compute(frame->left, frame->right, T_world_camera, 0, frame->raw_noise_sigma));
    drive.T_world_camera.push_back(T_world_camera);
  }
  for (const auto& cloud : drive.clouds) {
    for (const auto& p : cloud.points) {
      drive.max_range_m = std::max(drive.max_range_m, static_cast<double>(p.norm()));
    }
  }
  return drive;
}

MapPair drivePair(const Drive& drive, size_t first_end, size_t second_begin, const Rigid3& T_extra,
                  double resolution) {
  const auto fuse = [&](size_t begin, size_t end, const Rigid3& T_own_world) {
    auto map = std::make_unique<OccupancyMap>(OccupancyMap::Options::octomapPreset(resolution));
    for (size_t i = begin; i < end && i < drive.clouds.size(); ++i) {
      map->insertCloud(drive.clouds[i], T_own_world * drive.T_world_camera[i],
                       drive.max_range_m + resolution);
    }
    return map;
  };
  MapPair pair;
  const Rigid3 T_a_world = drive.T_world_camera.front().inverse();
  const Rigid3 T_b_world = T_extra * drive.T_world_camera.at(second_begin).inverse();
  pair.a = fuse(0, first_end, T_a_world);
  pair.b = fuse(second_begin, drive.clouds.size(), T_b_world);
  pair.T_a_b = T_a_world * T_b_world.inverse();
  return pair;
}

MapPair windowPair(const OccupancyMap& whole, double width, double share, const Rigid3& T_b_world,
                   const Vec3& offset) {
  const common::Box3 bounds = whole.occupiedBounds();
  const Vec3 centre = (bounds.min + bounds.max) / 2 + offset;
  common::Box3 box_a{Vec3(centre.x() - width, centre.y() - width / 2, bounds.min.z()),
                     Vec3(centre.x(), centre.y() + width / 2, bounds.max.z())};
  common::Box3 box_b = box_a;
  box_b.min.x() += (1 - share) * width;
  box_b.max.x() += (1 - share) * width;
  return cutPair(whole, box_a, box_b, T_b_world);
}

std::unique_ptr<OccupancyMap> corridorMap(double x0, double x1, double pitch,
                                          const Rigid3& T_own_world, double resolution) {
  constexpr double kHalfWidth = 1.2, kHeight = 3.0, kPillar = 0.4;
  const double step = resolution / 2;
  const auto pillarAt = [&](double x) {
    if (pitch <= 0) return false;
    const double phase = x - pitch * std::floor(x / pitch);
    return phase < kPillar;
  };
  std::vector<Vec3> occupied, free;
  for (double x = x0; x < x1; x += step) {
    for (double y = -kHalfWidth; y <= kHalfWidth; y += step)
      occupied.push_back(T_own_world * Vec3(x, y, 0));
    for (double z = 0; z <= kHeight; z += step) {
      occupied.push_back(T_own_world * Vec3(x, -kHalfWidth, z));
      occupied.push_back(T_own_world * Vec3(x, kHalfWidth, z));
      if (pillarAt(x)) occupied.push_back(T_own_world * Vec3(x, kHalfWidth - kPillar, z));
    }
    if (pillarAt(x)) {
      for (double y = kHalfWidth - kPillar; y <= kHalfWidth; y += step) {
        for (double z = 0; z <= kHeight; z += step) occupied.push_back(T_own_world * Vec3(x, y, z));
      }
    }
    for (double y = -kHalfWidth + 2 * resolution; y <= kHalfWidth - kPillar - 2 * resolution;
         y += resolution) {
      for (double z = 2 * resolution; z <= kHeight; z += resolution) {
        free.push_back(T_own_world * Vec3(x, y, z));
      }
    }
  }
  return mapOfPoints(resolution, occupied, free);
}

Rigid3 poseOf(double yaw_deg, const Vec3& t, double roll_deg, double pitch_deg) {
  const double deg = M_PI / 180;
  const common::Quat q = Eigen::AngleAxisd(yaw_deg * deg, Vec3::UnitZ()) *
                         Eigen::AngleAxisd(pitch_deg * deg, Vec3::UnitY()) *
                         Eigen::AngleAxisd(roll_deg * deg, Vec3::UnitX());
  return {q, t};
}

PoseError poseError(const Rigid3& estimate, const Rigid3& truth) {
  const Rigid3 delta = truth.inverse() * estimate;
  return {delta.translation.norm(),
          Eigen::AngleAxisd(delta.rotation.normalized()).angle() * 180 / M_PI};
}

}  // namespace stereomap::testing
