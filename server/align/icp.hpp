// Point-to-plane ICP as Open3D's RegistrationICP runs it (the same linearised step, the same
// correspondences: each source point's nearest target point within reach, the same stop),
// on a k-d tree the caller already has: Open3D builds one for every call, which cost more than
// the iterations on the alignment's many candidate poses.
//
//   const auto fit = align::icpPointToPlane(points_b, cloud_a, tree_a, 2.0 * edge, T, 20, 1e-6);
//   fit.T_target_source, fit.matched, fit.rmse
#pragma once

#include <Eigen/Core>

#include <cstddef>
#include <vector>

#include <open3d/geometry/KDTreeFlann.h>
#include <open3d/geometry/PointCloud.h>

namespace stereomap::align {

struct IcpFit {
  Eigen::Matrix4d T_target_source = Eigen::Matrix4d::Identity();
  size_t matched = 0;  // source points with a target point within reach, at the last pose
  double rmse = 0;     // their distances' root mean square
};

// `target` needs normals and `tree` is built over it. Stops after `max_iterations`, or when
// both the matched share and the RMSE change by less than `tolerance` in one iteration.
IcpFit icpPointToPlane(const std::vector<Eigen::Vector3d>& source,
                       const open3d::geometry::PointCloud& target,
                       const open3d::geometry::KDTreeFlann& tree, double reach,
                       const Eigen::Matrix4d& initial, int max_iterations, double tolerance);

}  // namespace stereomap::align
