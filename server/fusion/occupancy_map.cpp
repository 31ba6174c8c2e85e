#include "server/fusion/occupancy_map.hpp"

#include <octomap/OcTree.h>

#include "server/fusion/detail/bulk_insert.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <istream>
#include <sstream>

namespace stereomap::fusion {

OccupancyMap::Options OccupancyMap::Options::octomapPreset(double resolution) {
  Options options;
  options.resolution = resolution;
  return options;
}

OccupancyMap::Options OccupancyMap::Options::paperPreset(double resolution) {
  Options options;
  options.resolution = resolution;
  options.prob_hit = 0.7;
  options.prob_miss = 0.1;
  options.occupancy_threshold = 0.6;
  options.free_threshold = 0.4;
  return options;
}

struct OccupancyMap::Impl {
  explicit Impl(const Options& options) : options(options), tree(options.resolution) {
    tree.setProbHit(options.prob_hit);
    tree.setProbMiss(options.prob_miss);
    tree.setClampingThresMin(options.clamp_min);
    tree.setClampingThresMax(options.clamp_max);
    tree.setOccupancyThres(options.occupancy_threshold);
  }
  // The fast path's second thread: the options' pool, else one of the map's own, started at
  // the first insertion (a map that is only loaded, queried or exported starts none).
  common::WorkerPool* pool() {
    if (options.pool == nullptr && options.threads >= 2) {
      own_pool = std::make_unique<common::WorkerPool>(1);
      options.pool = own_pool.get();
    }
    return options.pool;
  }
  std::unique_ptr<common::WorkerPool> own_pool;
  Options options;
  detail::BulkOcTree tree;
};

OccupancyMap::OccupancyMap(const Options& options) : impl_(std::make_unique<Impl>(options)) {}
OccupancyMap::~OccupancyMap() = default;

void OccupancyMap::insertCloud(const common::PointCloud& cloud_sensor,
                               const common::Rigid3& T_map_sensor, double max_range_m,
                               MapChanges* changes) {
  // OctoMap's keys span 2^16 voxels per axis around the map's origin, and its coordToKey
  // casts to int before it checks the range: a coordinate beyond int's range (or inf, or NaN)
  // is undefined behaviour there, not a miss. So a sensor outside the map inserts nothing, and
  // rays longer than twice the map's diagonal are cut to that length in double precision:
  // they still cross the whole map, and their ends lie outside it either way.
  const common::Vec3& t = T_map_sensor.translation;
  const double extent = impl_->tree.getResolution() * 32768.0;
  if (!(t.array().abs() < extent).all()) {  // (false for NaN, which maxCoeff may skip)
    if (changes != nullptr) *changes = {.complete = true, .voxels = {}};
    return;
  }
  const double longest = 4 * std::sqrt(3.0) * extent;
  std::vector<octomap::point3d> points;
  points.reserve(cloud_sensor.size());
  for (const auto& p : cloud_sensor.points) {
    common::Vec3 p_map = T_map_sensor * p.cast<double>();
    if (!p_map.allFinite()) continue;
    if (const double length = (p_map - t).norm(); length > longest) {
      p_map = t + (p_map - t) * (longest / length);
    }
    points.emplace_back(static_cast<float>(p_map.x()), static_cast<float>(p_map.y()),
                        static_cast<float>(p_map.z()));
  }
  const octomap::point3d origin(static_cast<float>(t.x()), static_cast<float>(t.y()),
                                static_cast<float>(t.z()));
  if (impl_->options.insertion == Insertion::kFast) {
    // Scratch buffers (several MB) live with the thread, so that a fusion worker reuses
    // them across frames and maps instead of faulting fresh pages in every time.
    thread_local detail::BulkInserter inserter;
    inserter.insert(impl_->tree, points, origin, max_range_m, impl_->options.threads, impl_->pool(),
                    changes != nullptr ? &changes->voxels : nullptr);
    if (changes != nullptr) changes->complete = true;
  } else {
    if (changes != nullptr) *changes = {.complete = false, .voxels = {}};
    octomap::Pointcloud scan;
    scan.reserve(points.size());
    for (const auto& p : points) scan.push_back(p);
    impl_->tree.insertPointCloud(scan, origin, max_range_m, /*lazy_eval=*/false,
                                 /*discretize=*/false);
  }
}

Occupancy OccupancyMap::query(const common::Vec3& p_map) const {
  // (OctoMap's search casts to int unchecked: see insertCloud.)
  if (!(p_map.array().abs() < impl_->tree.getResolution() * 32768.0).all()) {
    return Occupancy::kUnknown;
  }
  const octomap::OcTreeNode* node = impl_->tree.search(p_map.x(), p_map.y(), p_map.z());
  if (node == nullptr) return Occupancy::kUnknown;
  if (impl_->tree.isNodeOccupied(node)) return Occupancy::kOccupied;
  return node->getOccupancy() <= impl_->options.free_threshold ? Occupancy::kFree
                                                               : Occupancy::kUnknown;
}

void OccupancyMap::visitKnown(const common::Box3& box, const LeafVisitor& visit) const {
  if (box.empty()) return;
  // Clipped to the tree's key range (OctoMap's coordToKey is unchecked: see insertCloud).
  const double limit = impl_->tree.getResolution() * 32767.0;
  const common::Vec3 low = box.min.cwiseMax(-limit), high = box.max.cwiseMin(limit);
  if ((low.array() > high.array()).any()) return;
  auto& tree = impl_->tree;
  for (auto it = tree.begin_leafs_bbx(octomap::point3d(low.x(), low.y(), low.z()),
                                      octomap::point3d(high.x(), high.y(), high.z())),
            end = tree.end_leafs_bbx();
       it != end; ++it) {
    const double edge = it.getSize();
    const common::Vec3 corner(it.getX() - edge / 2, it.getY() - edge / 2, it.getZ() - edge / 2);
    Occupancy occupancy = Occupancy::kUnknown;
    if (tree.isNodeOccupied(*it)) {
      occupancy = Occupancy::kOccupied;
    } else if (it->getOccupancy() <= impl_->options.free_threshold) {
      occupancy = Occupancy::kFree;
    }
    if (occupancy != Occupancy::kUnknown) visit(corner, edge, occupancy);
  }
}

std::vector<VoxelIndex> OccupancyMap::occupiedCells(unsigned depth) const {
  depth = std::clamp(depth, 1u, kTreeDepth);
  const auto& tree = impl_->tree;
  const unsigned shift = kTreeDepth - depth;
  const int32_t offset = kKeyOffset >> shift;
  std::vector<VoxelIndex> cells;
  for (auto it = tree.begin_leafs(depth), end = tree.end_leafs(); it != end; ++it) {
    if (!tree.isNodeOccupied(*it)) continue;
    const octomap::OcTreeKey key = it.getKey();
    // A leaf above `depth` (pruned) covers several cells of that depth.
    const int32_t span = 1 << (depth - std::min(depth, it.getDepth()));
    const int32_t x0 = (key[0] >> shift & ~(span - 1)) - offset;
    const int32_t y0 = (key[1] >> shift & ~(span - 1)) - offset;
    const int32_t z0 = (key[2] >> shift & ~(span - 1)) - offset;
    for (int32_t dx = 0; dx < span; ++dx) {
      for (int32_t dy = 0; dy < span; ++dy) {
        for (int32_t dz = 0; dz < span; ++dz) cells.push_back({x0 + dx, y0 + dy, z0 + dz});
      }
    }
  }
  std::sort(cells.begin(), cells.end());
  return cells;
}

double OccupancyMap::cellSize(unsigned depth) const {
  return impl_->tree.getNodeSize(std::clamp(depth, 1u, kTreeDepth));
}

std::vector<VoxelIndex> OccupancyMap::occupiedVoxelsIn(const common::Box3& box) const {
  std::vector<VoxelIndex> inside;
  if (box.empty()) return inside;
  const auto& tree = impl_->tree;
  const octomap::point3d lo(static_cast<float>(box.min.x()), static_cast<float>(box.min.y()),
                            static_cast<float>(box.min.z()));
  const octomap::point3d hi(static_cast<float>(box.max.x()), static_cast<float>(box.max.y()),
                            static_cast<float>(box.max.z()));
  for (auto it = tree.begin_leafs_bbx(lo, hi), end = tree.end_leafs_bbx(); it != end; ++it) {
    if (!tree.isNodeOccupied(*it)) continue;
    const octomap::OcTreeKey key = it.getKey();
    const int32_t span = 1 << (kTreeDepth - it.getDepth());
    for (int32_t dx = 0; dx < span; ++dx) {
      for (int32_t dy = 0; dy < span; ++dy) {
        for (int32_t dz = 0; dz < span; ++dz) {
          const VoxelIndex v{(key[0] & ~(span - 1)) - kKeyOffset + dx,
                             (key[1] & ~(span - 1)) - kKeyOffset + dy,
                             (key[2] & ~(span - 1)) - kKeyOffset + dz};
          if (box.contains(voxelCentre(v))) inside.push_back(v);
        }
      }
    }
  }
  std::sort(inside.begin(), inside.end());
  return inside;
}

namespace {
// Occupied nodes below `node` (at `depth`, first voxel `code`) in code order: children in
// index order are in code order (child bit 0 is x, as in the code).
void visitOccupiedRecurs(const octomap::OcTree& tree, const octomap::OcTreeNode* node,
                         unsigned depth, uint64_t code,
                         const OccupancyMap::OccupiedVisitor& visit) {
  if (!tree.nodeHasChildren(node)) {
    if (tree.isNodeOccupied(node)) visit(code, depth, detail::occupancyByte(node->getLogOdds()));
    return;
  }
  const unsigned child_shift = 3 * (kTreeDepth - depth - 1);
  for (unsigned i = 0; i < 8; ++i) {
    if (!tree.nodeChildExists(node, i)) continue;
    visitOccupiedRecurs(tree, tree.getNodeChild(node, i), depth + 1,
                        code | uint64_t{i} << child_shift, visit);
  }
}
}  // namespace

void OccupancyMap::visitOccupied(uint64_t code, unsigned depth,
                                 const OccupiedVisitor& visit) const {
  const auto& tree = impl_->tree;
  const octomap::OcTreeNode* node = tree.getRoot();
  if (node == nullptr || depth > kTreeDepth) return;
  code &= ~((uint64_t{1} << 3 * (kTreeDepth - depth)) - 1);  // the node's first voxel
  // Down to the node; a leaf on the way (pruned) covers it: report the part inside it.
  for (unsigned d = 0; d < depth; ++d) {
    if (!tree.nodeHasChildren(node)) {
      if (tree.isNodeOccupied(node)) visit(code, depth, detail::occupancyByte(node->getLogOdds()));
      return;
    }
    const auto child = static_cast<unsigned>(code >> 3 * (kTreeDepth - d - 1) & 7);
    if (!tree.nodeChildExists(node, child)) return;
    node = tree.getNodeChild(node, child);
  }
  visitOccupiedRecurs(tree, node, depth, code, visit);
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

bool OccupancyMap::writeFull(std::ostream& out) const { return impl_->tree.write(out); }

namespace {

using common::ErrorCode;
using common::makeError;

constexpr size_t kMaxMapFileBytes = size_t{4} << 30;

enum class TreeFormat { kBinary, kFull };

struct TreeFile {
  TreeFormat format = TreeFormat::kFull;
  double resolution = 0;
  uint64_t nodes = 0;  // the header's node count
  std::string data;    // the bytes after "data"
};

// The header of OctoMap's .bt and .ot files: a first line naming the format, comment lines,
// then "id", "size", "res" and "data" lines (AbstractOcTree::readHeader).
common::Result<TreeFile> readTreeFile(std::istream& in) {
  TreeFile file;
  std::string line;
  if (!std::getline(in, line)) return makeError(ErrorCode::kCorrupt, "the file is empty");
  if (line.rfind("# Octomap OcTree binary file", 0) == 0) {
    file.format = TreeFormat::kBinary;
  } else if (line.rfind("# Octomap OcTree file", 0) == 0) {
    file.format = TreeFormat::kFull;
  } else {
    return makeError(ErrorCode::kCorrupt,
                     "not an OctoMap file (its first line is not '# Octomap OcTree binary file' "
                     "or '# Octomap OcTree file')");
  }
  std::string id;
  bool has_size = false, has_data = false;
  for (int lines = 0; lines < 1000 && std::getline(in, line); ++lines) {
    if (line.empty() || line[0] == '#') continue;
    std::istringstream fields(line);
    std::string key;
    fields >> key;
    if (key == "id") fields >> id;
    if (key == "res") fields >> file.resolution;
    if (key == "size") has_size = static_cast<bool>(fields >> file.nodes);
    if (key == "data") {
      has_data = true;
      break;
    }
  }
  if (!has_data || !has_size) {
    return makeError(ErrorCode::kCorrupt, "the OctoMap header has no 'size' or 'data' line");
  }
  if (id != "OcTree") {
    return makeError(ErrorCode::kCorrupt,
                     "not an occupancy OcTree (id '" + id.substr(0, 40) + "')");
  }
  if (!(file.resolution >= 1e-4 && file.resolution <= 100)) {
    return makeError(ErrorCode::kCorrupt, "resolution out of range (0.0001 .. 100 m)");
  }
  std::ostringstream data;
  data << in.rdbuf();
  file.data = data.str();
  if (file.data.size() > kMaxMapFileBytes) return makeError(ErrorCode::kTooLarge, "file too large");
  return file;
}

// Walks the node structure OctoMap's reader would follow (readBinaryNode/readNodesRecurs,
// which check nothing) and tells whether it stays inside the bytes and the tree's 16 levels.
class TreeDataCheck {
 public:
  TreeDataCheck(const TreeFile& file) : file_(file) {}
  common::Status run() {
    if (file_.nodes == 0) {
      if (!file_.data.empty()) return makeError(ErrorCode::kCorrupt, "data after an empty tree");
      return common::Ok{};
    }
    if (!(file_.format == TreeFormat::kBinary ? binaryNode(0) : fullNode(0))) {
      return makeError(ErrorCode::kCorrupt, problem_);
    }
    if (at_ != file_.data.size()) {
      return makeError(ErrorCode::kCorrupt, std::to_string(file_.data.size() - at_) +
                                                " bytes after the tree's last node");
    }
    if (nodes_ != file_.nodes) {
      return makeError(ErrorCode::kCorrupt, "the tree holds " + std::to_string(nodes_) +
                                                " nodes, its header says " +
                                                std::to_string(file_.nodes));
    }
    return common::Ok{};
  }

 private:
  bool take(size_t bytes) {
    if (file_.data.size() - at_ < bytes) {
      problem_ = "the map data is truncated";
      return false;
    }
    at_ += bytes;
    return true;
  }
  // .bt: two bytes per inner node, two bits per child (11: it has children).
  bool binaryNode(unsigned depth) {
    ++nodes_;
    const size_t at = at_;
    if (!take(2)) return false;
    const unsigned bits = static_cast<uint8_t>(file_.data[at]) |
                          static_cast<unsigned>(static_cast<uint8_t>(file_.data[at + 1])) << 8;
    for (unsigned i = 0; i < 8; ++i) {
      const unsigned child = (bits >> (2 * i)) & 3;
      if (child == 0) continue;
      if (child != 3) {
        ++nodes_;
        continue;
      }
      if (depth + 1 >= kTreeDepth) {
        problem_ = "the map data goes deeper than 16 levels";
        return false;
      }
      if (!binaryNode(depth + 1)) return false;
    }
    return true;
  }
  // .ot: a float log-odds and a child bit mask per node.
  bool fullNode(unsigned depth) {
    ++nodes_;
    const size_t at = at_;
    if (!take(5)) return false;
    float log_odds;
    std::memcpy(&log_odds, file_.data.data() + at, 4);
    if (!std::isfinite(log_odds)) {
      problem_ = "the map data holds a value that is not a number";
      return false;
    }
    const auto children = static_cast<uint8_t>(file_.data[at + 4]);
    if (children != 0 && depth >= kTreeDepth) {
      problem_ = "the map data goes deeper than 16 levels";
      return false;
    }
    for (unsigned i = 0; i < 8; ++i) {
      if ((children >> i & 1) && !fullNode(depth + 1)) return false;
    }
    return true;
  }

  const TreeFile& file_;
  size_t at_ = 0;
  uint64_t nodes_ = 0;
  std::string problem_;
};

}  // namespace

common::Status OccupancyMap::readFull(std::istream& in) {
  auto& tree = impl_->tree;
  tree.clear();
  auto file = readTreeFile(in);
  if (!file) return file.error();
  if (file->format != TreeFormat::kFull) {
    return makeError(ErrorCode::kCorrupt, "a .bt file, not a .ot snapshot");
  }
  if (std::abs(file->resolution - tree.getResolution()) > 1e-9) {
    return makeError(ErrorCode::kInvalidArgument, "resolution " + std::to_string(file->resolution) +
                                                      " differs from the map's " +
                                                      std::to_string(tree.getResolution()));
  }
  if (auto checked = TreeDataCheck(*file).run(); !checked) return checked;
  if (file->nodes > 0) {
    std::istringstream data(std::move(file->data));
    tree.readData(data);
  }
  return common::Ok{};
}

common::Result<std::unique_ptr<OccupancyMap>> OccupancyMap::load(std::istream& in) {
  return load(in, Options{});
}

common::Result<std::unique_ptr<OccupancyMap>> OccupancyMap::load(std::istream& in,
                                                                 Options options) {
  auto file = readTreeFile(in);
  if (!file) return file.error();
  if (auto checked = TreeDataCheck(*file).run(); !checked) return checked.error();
  options.resolution = file->resolution;
  auto map = std::make_unique<OccupancyMap>(options);
  if (file->nodes > 0) {
    std::istringstream data(std::move(file->data));
    if (file->format == TreeFormat::kBinary) {
      map->impl_->tree.readBinaryData(data);
    } else {
      map->impl_->tree.readData(data);
    }
  }
  return map;
}

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

namespace {

using Node = octomap::OcTreeNode;

Occupancy classOf(const octomap::OcTree& tree, const Node* node) {
  if (node == nullptr) return Occupancy::kUnknown;
  return tree.isNodeOccupied(node) ? Occupancy::kOccupied : Occupancy::kFree;
}

// A node's child, or the node itself when it is a leaf (its class covers the child's region).
const Node* childOrSelf(const octomap::OcTree& tree, const Node* node, unsigned i) {
  if (node == nullptr || !tree.nodeHasChildren(node)) return node;
  return tree.nodeChildExists(node, i) ? tree.getNodeChild(node, i) : nullptr;
}

void compareRecurs(const octomap::OcTree& ta, const Node* a, const octomap::OcTree& tb,
                   const Node* b, unsigned depth, MapAgreement& result) {
  if (a == nullptr && b == nullptr) return;
  const bool a_split = a != nullptr && ta.nodeHasChildren(a);
  const bool b_split = b != nullptr && tb.nodeHasChildren(b);
  if (a_split || b_split) {
    for (unsigned i = 0; i < 8; ++i) {
      compareRecurs(ta, childOrSelf(ta, a, i), tb, childOrSelf(tb, b, i), depth + 1, result);
    }
    return;
  }
  const uint64_t voxels = uint64_t{1} << (3 * (16 - depth));
  result.voxels += voxels;
  if (classOf(ta, a) == classOf(tb, b)) result.agreeing += voxels;
}

}  // namespace

MapAgreement compareClassification(const OccupancyMap& a, const OccupancyMap& b) {
  MapAgreement result;
  compareRecurs(a.impl_->tree, a.impl_->tree.getRoot(), b.impl_->tree, b.impl_->tree.getRoot(), 0,
                result);
  return result;
}

}  // namespace stereomap::fusion
