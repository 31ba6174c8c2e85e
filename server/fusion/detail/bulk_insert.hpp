// The fast insertion path behind OccupancyMap (internal to server/fusion). It produces the
// same update as OctoMap's insertPointCloud (same rays, same "occupied wins over free"
// rule, one log-odds update per touched voxel) at a fraction of the cost:
//  1. rays are cast on all cores into dense bitsets over the cloud's bounding box (no
//     std::unordered_set), one bitset per thread, eight rays at a time where the CPU has
//     AVX2 (detail/ray_cast);
//  2. the touched voxels are gathered into 4x4x4 bricks and listed in Morton order (a radix
//     sort of the bricks only), so that
//  3. the tree is updated in one recursive descent that visits each touched subtree once,
//     updating inner nodes and pruning on the way back up (no per-key updateNode()).
#pragma once

#include <octomap/OcTree.h>

#include <cstdint>
#include <functional>
#include <vector>

#include "common/worker_pool.hpp"
#include "server/fusion/detail/ray_cast.hpp"
#include "server/fusion/voxel_code.hpp"

namespace stereomap::fusion::detail {

// round(255 * P) for log-odds L (P = 1 / (1 + e^-L)).
uint8_t occupancyByte(float log_odds);

// Runs two halves of a step: on the pool when there is one, else one after the other here.
void runTwo(common::WorkerPool* pool, const std::function<void()>& first,
            const std::function<void()>& second);

// octomap::OcTree with a bulk update (it needs the tree's protected root).
class BulkOcTree : public octomap::OcTree {
 public:
  explicit BulkOcTree(double resolution) : octomap::OcTree(resolution) {}
  // `codes`: Morton code of each key shifted left by one, lowest bit set for an occupied
  // (hit) update and clear for a free (miss) update; sorted ascending, no key twice.
  // threads >= 2: subtrees below depth 3 are updated on two threads (`pool`'s, or threads
  // of their own when it is null). `changes` (optional) receives every node whose class or
  // value changed, sorted by code.
  void applySortedUpdates(const std::vector<uint64_t>& codes, unsigned threads = 1,
                          common::WorkerPool* pool = nullptr,
                          std::vector<VoxelChange>* changes = nullptr);

 private:
  struct Task {
    octomap::OcTreeNode* node;
    bool just_created;
    const uint64_t* begin;
    const uint64_t* end;
  };
  void descend(octomap::OcTreeNode* node, bool node_just_created, unsigned depth,
               const uint64_t* begin, const uint64_t* end);
  // The child to descend into exists afterwards; true when it had to be created.
  bool openChild(octomap::OcTreeNode* node, bool node_just_created, unsigned child);
  void openTop(octomap::OcTreeNode* node, bool node_just_created, unsigned depth,
               const uint64_t* begin, const uint64_t* end, std::vector<Task>& tasks);
  void closeTop(octomap::OcTreeNode* node, unsigned depth, const uint64_t* begin,
                const uint64_t* end);
  // True when `node` is at the clamping bound that every update in [begin, end) pushes
  // towards (all misses at the lower bound, or all hits at the upper): none can change it.
  bool clampedForAll(const octomap::OcTreeNode* node, const uint64_t* begin,
                     const uint64_t* end) const;
  // Records a node's update in changes_ when its class or quantised value moved.
  void noteChange(uint64_t code, unsigned depth, bool just_created, float before, float after);

  std::vector<VoxelChange>* changes_ = nullptr;
};

// Reusable buffers for insertions (one per map; not thread-safe).
class BulkInserter {
 public:
  // Points in the map frame; rays from `origin`, clipped at max_range (< 0: no limit).
  // `changes` (optional): as BulkOcTree::applySortedUpdates.
  void insert(BulkOcTree& tree, const std::vector<octomap::point3d>& points,
              const octomap::point3d& origin, double max_range, unsigned threads,
              common::WorkerPool* pool = nullptr, std::vector<VoxelChange>* changes = nullptr);

 private:
  std::vector<uint64_t> free_bits_[2], occupied_bits_;
  std::vector<TouchedBrick> bricks_;
  std::vector<uint64_t> order_, codes_, scratch_;
  std::vector<uint32_t> counts_;
};

// Morton code of a key: bit b of x, y, z at bits 3b, 3b+1, 3b+2.
uint64_t mortonCode(const octomap::OcTreeKey& key);
octomap::OcTreeKey mortonDecode(uint64_t code);

}  // namespace stereomap::fusion::detail
