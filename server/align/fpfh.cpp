#include "server/align/fpfh.hpp"

#include <algorithm>
#include <cmath>
#include <vector>

namespace stereomap::align {

namespace {

constexpr int kBins = 11;

// The three angles of the pair (p1, n1), (p2, n2) in the Darboux frame of the one whose normal
// is closer to the line between them, each mapped to a bin. False when the frame is undefined.
bool pairBins(const Eigen::Vector3d& p1, const Eigen::Vector3d& n1, const Eigen::Vector3d& p2,
              const Eigen::Vector3d& n2, int bins[3]) {
  Eigen::Vector3d line = p2 - p1;
  const double length = line.norm();
  if (length == 0.0) return false;
  const double cos1 = n1.dot(line) / length, cos2 = n2.dot(line) / length;
  const Eigen::Vector3d* u = &n1;
  const Eigen::Vector3d* other = &n2;
  double phi = cos1;
  if (std::acos(std::fabs(cos1)) > std::acos(std::fabs(cos2))) {
    u = &n2, other = &n1, line = -line, phi = -cos2;
  }
  Eigen::Vector3d v = line.cross(*u);
  const double v_norm = v.norm();
  if (v_norm == 0.0) return false;
  v /= v_norm;
  const Eigen::Vector3d w = u->cross(v);
  const double alpha = v.dot(*other);
  const double theta = std::atan2(w.dot(*other), u->dot(*other));
  const auto bin = [](double value) {
    return std::clamp(static_cast<int>(std::floor(value)), 0, kBins - 1);
  };
  bins[0] = bin(kBins * (theta + M_PI) / (2.0 * M_PI));
  bins[1] = bin(kBins * (alpha + 1.0) * 0.5);
  bins[2] = bin(kBins * (phi + 1.0) * 0.5);
  return true;
}

}  // namespace

FpfhFeatures fpfhFeatures(const open3d::geometry::PointCloud& cloud,
                          const open3d::geometry::KDTreeFlann& tree, double radius,
                          int max_neighbours) {
  const auto n = static_cast<int>(cloud.points_.size());
  // Each point's neighbours (itself first), kept for the second pass: rows of max_neighbours.
  std::vector<int> neighbours(static_cast<size_t>(n) * max_neighbours);
  std::vector<double> distance2(neighbours.size());
  std::vector<int> count(n);
  FpfhFeatures simple = FpfhFeatures::Zero(33, n);
#pragma omp parallel
  {
    std::vector<int> found;
    std::vector<double> found2;
#pragma omp for schedule(static)
    for (int i = 0; i < n; ++i) {
      const int k = tree.SearchHybrid(cloud.points_[i], radius, max_neighbours, found, found2);
      count[i] = k;
      std::copy_n(found.begin(), k,
                  neighbours.begin() + static_cast<ptrdiff_t>(i) * max_neighbours);
      std::copy_n(found2.begin(), k,
                  distance2.begin() + static_cast<ptrdiff_t>(i) * max_neighbours);
      if (k <= 1) continue;
      const double step = 100.0 / (k - 1);
      for (int m = 1; m < k; ++m) {
        const int j = found[m];
        int bins[3];
        if (!pairBins(cloud.points_[i], cloud.normals_[i], cloud.points_[j], cloud.normals_[j],
                      bins)) {
          bins[0] = bins[1] = bins[2] = kBins / 2;  // an undefined frame's angles are zero
        }
        for (int angle = 0; angle < 3; ++angle) simple(angle * kBins + bins[angle], i) += step;
      }
    }
  }
  FpfhFeatures features = FpfhFeatures::Zero(33, n);
#pragma omp parallel for schedule(static)
  for (int i = 0; i < n; ++i) {
    if (count[i] <= 1) continue;
    const int* around = neighbours.data() + static_cast<ptrdiff_t>(i) * max_neighbours;
    const double* around2 = distance2.data() + static_cast<ptrdiff_t>(i) * max_neighbours;
    double sum[3] = {0, 0, 0};
    for (int m = 1; m < count[i]; ++m) {
      if (around2[m] == 0.0) continue;
      for (int bin = 0; bin < 33; ++bin) {
        const double value = simple(bin, around[m]) / around2[m];
        sum[bin / kBins] += value;
        features(bin, i) += value;
      }
    }
    for (double& s : sum) s = s != 0 ? 100.0 / s : s;
    for (int bin = 0; bin < 33; ++bin) {
      features(bin, i) = features(bin, i) * sum[bin / kBins] + simple(bin, i);
    }
  }
  return features;
}

}  // namespace stereomap::align
