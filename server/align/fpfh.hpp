// FPFH features (Rusu, Blodow and Beetz, ICRA 2009) of a map's occupied cells, computed as
// Open3D's ComputeFPFHFeature computes them (33 bins: 11 for each of the three angles of a
// Darboux frame, each point's own histogram plus its neighbours' weighted by 1 / distance^2),
// but with one neighbour search a point shared by both passes, on the caller's k-d tree.
// Each point's feature depends on nothing but the cloud: any number of OpenMP threads gives the
// same features.
//
//   const auto features = align::fpfhFeatures(cloud, tree, 5.0 * edge, 50);  // 33 x N
#pragma once

#include <Eigen/Core>

#include <open3d/geometry/KDTreeFlann.h>
#include <open3d/geometry/PointCloud.h>

namespace stereomap::align {

using FpfhFeatures = Eigen::Matrix<double, 33, Eigen::Dynamic>;

// `cloud` needs normals; `tree` is built over `cloud`. Neighbours: at most `max_neighbours`
// (the point itself among them) within `radius`.
FpfhFeatures fpfhFeatures(const open3d::geometry::PointCloud& cloud,
                          const open3d::geometry::KDTreeFlann& tree, double radius,
                          int max_neighbours);

}  // namespace stereomap::align
