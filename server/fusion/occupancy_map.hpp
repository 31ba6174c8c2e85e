// One session's occupancy map: an OctoMap octree behind a small interface (OctoMap's API
// does not leak). Clouds are inserted with their sensor pose; the map answers which voxels
// are occupied, their bounds, and exports OctoMap's binary .bt format.
//
//   OccupancyMap map({.resolution = 0.1});
//   map.insertCloud(cloud_camera, T_map_camera, /*max_range=*/6.0);
//   for (VoxelIndex v : map.occupiedVoxels()) ...
#pragma once

#include <cstdint>
#include <functional>
#include <iosfwd>
#include <memory>
#include <vector>

#include "common/geometry.hpp"
#include "common/point_cloud.hpp"
#include "common/result.hpp"
#include "common/worker_pool.hpp"
#include "server/fusion/voxel_code.hpp"

namespace stereomap::fusion {

enum class Occupancy { kUnknown, kFree, kOccupied };

// How two maps classify the voxels that either of them knows, counted in finest voxels.
struct MapAgreement {
  uint64_t voxels = 0;    // known (free or occupied) in at least one map
  uint64_t agreeing = 0;  // same class in both
  double fraction() const { return voxels ? static_cast<double>(agreeing) / voxels : 1.0; }
};

// What one insertion changed: every voxel or block whose class or quantised value moved,
// sorted by code, so that tiles and counts follow the map without walking it.
struct MapChanges {
  // False when the insertion path cannot tell (Insertion::kOctomap): anything may have changed.
  bool complete = true;
  std::vector<VoxelChange> voxels;
};

class OccupancyMap {
 public:
  enum class Insertion {
    kFast,     // ours: bitset ray casting on all cores + one bulk tree update (default)
    kOctomap,  // OctoMap's own insertPointCloud, for comparison
  };

  // Sensor model; the defaults are OctoMap's (hit 0.7, miss 0.4, clamping 0.1192/0.971).
  struct Options {
    double resolution = 0.1;  // metres, finest voxel edge
    double prob_hit = 0.7;
    double prob_miss = 0.4;
    double clamp_min = 0.1192;
    double clamp_max = 0.971;
    double occupancy_threshold = 0.5;  // occupied when P >= this
    double free_threshold = 0.5;       // free when P <= this (and not occupied); else unknown
    Insertion insertion = Insertion::kFast;
    unsigned threads = 2;  // ray casting threads of the fast path
    // Where the fast path runs its second thread (not owned; it outlives the map); null: a
    // pool of one thread that lives with the map from its first insertion (no thread is
    // started per frame).
    common::WorkerPool* pool = nullptr;

    // OctoMap's defaults (above).
    static Options octomapPreset(double resolution);
    // The octree-mapping paper: hit 0.7, free 0.1; occupied if P >= 0.6 (free if <= 0.4,
    // unknown between: see classify()).
    static Options paperPreset(double resolution);
  };

  explicit OccupancyMap(const Options& options);
  ~OccupancyMap();
  OccupancyMap(const OccupancyMap&) = delete;
  OccupancyMap& operator=(const OccupancyMap&) = delete;

  // Inserts `cloud_sensor` (points in the sensor frame) seen from T_map_sensor: the voxels
  // along each ray become more free, the end voxel more occupied; rays longer than
  // `max_range_m` only clear free space up to that range. Same result as OctoMap's
  // insertPointCloud. `changes` (optional) receives what changed.
  void insertCloud(const common::PointCloud& cloud_sensor, const common::Rigid3& T_map_sensor,
                   double max_range_m, MapChanges* changes = nullptr);

  // The voxel's class: occupied (P >= occupancy_threshold), free (P <= free_threshold) or
  // unknown (never observed, or in between).
  Occupancy query(const common::Vec3& p_map) const;
  // Calls visit(code, depth, value) for every occupied node below the node of `depth` whose
  // first voxel has `code` (depth 0: the whole map), in code order: a voxel (depth 16) or a
  // pruned block of 2^(16 - depth) voxels per axis; value = round(255 P).
  using OccupiedVisitor = std::function<void(uint64_t code, unsigned depth, uint8_t value)>;
  void visitOccupied(uint64_t code, unsigned depth, const OccupiedVisitor& visit) const;
  // Occupied voxels at the finest resolution, sorted (pruned nodes are expanded).
  std::vector<VoxelIndex> occupiedVoxels() const;
  size_t occupiedCount() const;
  // Occupied cells at a coarser `depth` (16 = finest; one level up doubles the edge): a
  // cell is occupied when its most occupied voxel is (OctoMap keeps inner nodes at the max of
  // their children). Index i of a cell at depth d has its centre at (i + 0.5) * cellSize(d).
  std::vector<VoxelIndex> occupiedCells(unsigned depth) const;
  double cellSize(unsigned depth) const;
  // Occupied voxels (finest) inside the box, sorted.
  std::vector<VoxelIndex> occupiedVoxelsIn(const common::Box3& box) const;
  // Calls visit(min corner, edge, class) for every known node (a voxel or a pruned block)
  // that meets the box, in no particular order; unknown space has no node and is not visited.
  using LeafVisitor =
      std::function<void(const common::Vec3& min_corner, double edge, Occupancy occupancy)>;
  void visitKnown(const common::Box3& box, const LeafVisitor& visit) const;
  // Bounds of the occupied voxels' cells; empty when nothing is occupied.
  common::Box3 occupiedBounds() const;
  common::Vec3 voxelCentre(const VoxelIndex& index) const;
  double resolution() const;
  // OctoMap binary (.bt, opens in octovis); the live tree is not pruned or modified.
  bool writeBinary(std::ostream& out) const;
  // OctoMap full format (.ot: log-odds kept); the live tree is not modified.
  bool writeFull(std::ostream& out) const;
  // Replaces the map with a .ot written by writeFull (same resolution); the map is left
  // empty on failure, and the error says why.
  common::Status readFull(std::istream& in);
  // A map from an OctoMap file, .bt (binary: occupied/free only) or .ot (full), at the file's
  // own resolution (options' sensor model otherwise). The whole file is checked before the
  // tree is built: a truncated, damaged or hostile file is an error naming the problem.
  static common::Result<std::unique_ptr<OccupancyMap>> load(std::istream& in, Options options);
  static common::Result<std::unique_ptr<OccupancyMap>> load(std::istream& in);
  // Number of bytes the tree occupies in memory (OctoMap's estimate).
  size_t memoryBytes() const;

 private:
  friend MapAgreement compareClassification(const OccupancyMap& a, const OccupancyMap& b);
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// Walks both trees together (pruned nodes stand for all their voxels). Same resolution only.
MapAgreement compareClassification(const OccupancyMap& a, const OccupancyMap& b);

}  // namespace stereomap::fusion
