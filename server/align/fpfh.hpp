// FPFH features (Rusu, Blodow and Beetz, ICRA 2009) of a map's occupied cells, computed as
// Open3D's ComputeFPFHFeature computes them (33 bins: 11 for each of the three angles of a
// Darboux frame, each point's own histogram plus its neighbours' weighted by 1 / distance^2),
// but on neighbours the caller found once for both passes (CellRaster::around: the cells' 50
// nearest within 5 edges, as Open3D's hybrid search of radius 5 edges and 50, but for cells
// exactly at 5 edges, which it leaves out).
// Each point's feature depends on nothing but the cloud and its neighbours: any number of
// OpenMP threads gives the same features.
//
//   const auto features = align::fpfhFeatures(cloud, cells.around(5.0, 50));  // 33 x N
#pragma once

#include <Eigen/Core>

#include <open3d/geometry/PointCloud.h>

#include "server/align/space_raster.hpp"

namespace stereomap::align {

using FpfhFeatures = Eigen::Matrix<double, 33, Eigen::Dynamic>;

// `cloud` needs normals; `neighbours` are each point's, nearest first, the point itself first.
FpfhFeatures fpfhFeatures(const open3d::geometry::PointCloud& cloud,
                          const NeighbourRows& neighbours);

}  // namespace stereomap::align
