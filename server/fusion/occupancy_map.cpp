#include "server/fusion/occupancy_map.hpp"

#include <octomap/OcTree.h>

#include <algorithm>

namespace stereomap::fusion {

namespace {
// OctoMap keys are offset so that key 32768 starts at coordinate 0 (16-level tree).
constexpr int32_t kKeyOffset = 32768;
constexpr unsigned kTreeDepth = 16;
}  // namespace

struct OccupancyMap::Impl {
  explicit Impl(const Options& options) : tree(options.resolution) {
    tree.setProbHit(options.prob_hit);
    tree.setProbMiss(options.prob_miss);
    tree.setClampingThresMin(options.clamp_min);
    tree.setClampingThresMax(options.clamp_max);
    tree.setOccupancyThres(options.occupancy_threshold);
  }
  octomap::OcTree tree;
};

OccupancyMap::OccupancyMap(const Options& options) : impl_(std::make_unique<Impl>(options)) {}
OccupancyMap::~OccupancyMap() = default;

void OccupancyMap::insertCloud(const common::PointCloud& cloud_sensor,
                               const common::Rigid3& T_map_sensor, double max_range_m) {
  octomap::Pointcloud scan;
  scan.reserve(cloud_sensor.size());
  for (const auto& p : cloud_sensor.points) {
    const common::Vec3 p_map = T_map_sensor * p.cast<double>();
    scan.push_back(static_cast<float>(p_map.x()), static_cast<float>(p_map.y()),
                   static_cast<float>(p_map.z()));
  }
  const common::Vec3& origin = T_map_sensor.translation;
  impl_->tree.insertPointCloud(scan, octomap::point3d(origin.x(), origin.y(), origin.z()),
                               max_range_m, /*lazy_eval=*/false, /*discretize=*/true);
}

Occupancy OccupancyMap::query(const common::Vec3& p_map) const {
  const octomap::OcTreeNode* node = impl_->tree.search(p_map.x(), p_map.y(), p_map.z());
  if (node == nullptr) return Occupancy::kUnknown;
  return impl_->tree.isNodeOccupied(node) ? Occupancy::kOccupied : Occupancy::kFree;
}

std::vector<VoxelIndex> OccupancyMap::occupiedVoxels() const {
  std::vector<VoxelIndex> voxels;
  const auto& tree = impl_->tree;
  for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) {
    if (!tree.isNodeOccupied(*it)) continue;
    const octomap::OcTreeKey key = it.getKey();
    // A leaf above the finest depth stands for 2^(16-depth) voxels per axis.
    const int32_t span = 1 << (kTreeDepth - it.getDepth());
    const int32_t base_x = (key[0] & ~(span - 1)) - kKeyOffset;
    const int32_t base_y = (key[1] & ~(span - 1)) - kKeyOffset;
    const int32_t base_z = (key[2] & ~(span - 1)) - kKeyOffset;
    for (int32_t dx = 0; dx < span; ++dx) {
      for (int32_t dy = 0; dy < span; ++dy) {
        for (int32_t dz = 0; dz < span; ++dz) {
          voxels.push_back({base_x + dx, base_y + dy, base_z + dz});
        }
      }
    }
  }
  std::sort(voxels.begin(), voxels.end());
  return voxels;
}

size_t OccupancyMap::occupiedCount() const {
  size_t count = 0;
  const auto& tree = impl_->tree;
  for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) {
    if (tree.isNodeOccupied(*it)) {
      const size_t span = size_t{1} << (kTreeDepth - it.getDepth());
      count += span * span * span;
    }
  }
  return count;
}

common::Box3 OccupancyMap::occupiedBounds() const {
  common::Box3 bounds;
  const auto& tree = impl_->tree;
  for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) {
    if (!tree.isNodeOccupied(*it)) continue;
    const double half = it.getSize() / 2;
    const common::Vec3 centre(it.getX(), it.getY(), it.getZ());
    bounds.extend(centre - common::Vec3::Constant(half));
    bounds.extend(centre + common::Vec3::Constant(half));
  }
  return bounds;
}

common::Vec3 OccupancyMap::voxelCentre(const VoxelIndex& index) const {
  const double r = impl_->tree.getResolution();
  return {(index.x + 0.5) * r, (index.y + 0.5) * r, (index.z + 0.5) * r};
}

double OccupancyMap::resolution() const { return impl_->tree.getResolution(); }

bool OccupancyMap::writeBinary(std::ostream& out) const {
  // OctoMap's writeBinaryConst() writes this header too, but also chatters on stderr.
  const auto& tree = impl_->tree;
  out << "# Octomap OcTree binary file\n# (feel free to add / change comments, but leave the "
         "first line as it is!)\n#\n"
      << "id " << tree.getTreeType() << "\nsize " << tree.size() << "\nres " << tree.getResolution()
      << "\ndata\n";
  tree.writeBinaryData(out);
  return static_cast<bool>(out);
}

size_t OccupancyMap::memoryBytes() const { return impl_->tree.memoryUsage(); }

}  // namespace stereomap::fusion
