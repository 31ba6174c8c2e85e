// The fast insertion path behind OccupancyMap (internal to server/fusion). It produces the
// same update as OctoMap's insertPointCloud (same rays, same "occupied wins over free"
// rule, one log-odds update per touched voxel) at a fraction of the cost:
//  1. rays are cast on all cores into dense bitsets over the cloud's bounding box (no
//     std::unordered_set), one bitset per thread, eight rays at a time where the CPU has
//     AVX2 (detail/ray_cast);
//  2. the touched voxels are gathered into 4x4x4 bricks and listed in Morton order (a radix
//     sort of the bricks only), so that
//  3. the tree is updated in one recursive descent that visits each touched subtree once,
//     updating inner nodes and pruning on the way back up (no per-key updateNode()); down to
//     the bricks it splits ranges of bricks, below them bit masks.
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
  // `bricks`: the touched 4x4x4 bricks, sorted by code, none twice; a voxel marked in
  // `occupied` gets an occupied (hit) update, one marked in `any` only a free (miss) update.
  // threads >= 2: subtrees below depth 3 are updated on two threads (`pool`'s, or threads of
  // their own when it is null). `changes` (optional) receives every node whose class or value
  // changed, sorted by code.
  void applyBricks(const std::vector<TouchedBrick>& bricks, unsigned threads = 1,
                   common::WorkerPool* pool = nullptr, std::vector<VoxelChange>* changes = nullptr);

 private:
  using Brick = TouchedBrick;
  struct Task {
    octomap::OcTreeNode* node;
    bool just_created;
    const Brick* begin;
    const Brick* end;
  };
  // Nodes down to the bricks' depth (14), a range of bricks below each.
  void descend(octomap::OcTreeNode* node, bool node_just_created, unsigned depth,
               const Brick* begin, const Brick* end);
  // A brick's node (depth 14), its 2x2x2 octets (depth 15) and their voxels, from its masks
  // (`any`, `occupied`: a brick's 64 bits, or an octet's 8 at `first_bit`).
  void descendBrick(octomap::OcTreeNode* node, bool node_just_created, uint64_t brick_code,
                    uint64_t any, uint64_t occupied);
  void descendOctet(octomap::OcTreeNode* node, bool node_just_created, uint64_t first_voxel,
                    unsigned any, unsigned occupied);
  // The child to descend into exists afterwards; true when it had to be created.
  bool openChild(octomap::OcTreeNode* node, bool node_just_created, unsigned child);
  void openTop(octomap::OcTreeNode* node, bool node_just_created, unsigned depth,
               const Brick* begin, const Brick* end, std::vector<Task>& tasks);
  void closeTop(octomap::OcTreeNode* node, unsigned depth, const Brick* begin, const Brick* end);
  // Updates a childless node that stands for every voxel below it, when they all get the
  // same update (hit: `occupied`), as OctoMap would after updating and pruning them.
  void updateWhole(octomap::OcTreeNode* node, bool node_just_created, unsigned depth,
                   uint64_t first_voxel, bool occupied);
  // True when `node` is at the clamping bound that every update below it pushes towards (all
  // misses at the lower bound, or all hits at the upper): none can change it. `all_missed`,
  // `all_hit`: what the updates below it are.
  bool clamped(const octomap::OcTreeNode* node, bool all_missed, bool all_hit) const;
  // After a node's children were updated: pruned into it when they are alike, else its value
  // follows theirs.
  void close(octomap::OcTreeNode* node);
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
  std::vector<octomap::point3d> ends_;
  std::vector<uint8_t> hit_;
  std::vector<uint64_t> free_bits_[2], occupied_bits_[2];  // a pair per thread
  std::vector<TouchedBrick> bricks_[2], sorted_;
  std::vector<uint64_t> order_, scratch_;
  std::vector<uint32_t> counts_;
};

}  // namespace stereomap::fusion::detail
