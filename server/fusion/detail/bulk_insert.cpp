#include "server/fusion/detail/bulk_insert.hpp"

#include <algorithm>
#include <array>
#include <atomic>
#include <cassert>
#include <cmath>
#include <limits>

#include "server/fusion/detail/ray_cast.hpp"

namespace stereomap::fusion::detail {

using octomap::OcTreeKey;
using octomap::OcTreeNode;
using octomap::point3d;

namespace {

// LSD radix sort of 64-bit values whose set bits are below `bits`, 11 bits a pass: a frame
// touches some 10^4 bricks, for which 16-bit digits spent most of the time clearing counts.
// (Splitting it over two threads measured no faster: it is memory-bound.)
void radixSort(std::vector<uint64_t>& values, std::vector<uint64_t>& scratch,
               std::vector<uint32_t>& counts, unsigned bits) {
  constexpr unsigned kDigit = 11;
  constexpr uint64_t kMask = (uint64_t{1} << kDigit) - 1;
  scratch.resize(values.size());
  counts.resize(size_t{1} << kDigit);
  for (unsigned shift = 0; shift < bits; shift += kDigit) {
    std::fill(counts.begin(), counts.end(), 0);
    for (uint64_t v : values) ++counts[(v >> shift) & kMask];
    uint32_t sum = 0;
    for (auto& c : counts) {
      const uint32_t n = c;
      c = sum;
      sum += n;
    }
    for (uint64_t v : values) scratch[counts[(v >> shift) & kMask]++] = v;
    values.swap(scratch);
  }
}

}  // namespace

uint8_t occupancyByte(float log_odds) {
  return static_cast<uint8_t>(std::lround(255.0f / (1.0f + std::exp(-log_odds))));
}

void runTwo(common::WorkerPool* pool, const std::function<void()>& first,
            const std::function<void()>& second) {
  if (pool != nullptr) return pool->runPair(first, second);
  first();  // no helper to run it on: both halves here, one after the other
  second();
}

namespace {
// Subtrees at this depth are the units of parallel work (up to 512 of them).
constexpr unsigned kTaskDepth = 3;
// The depth of a brick's node: 4x4x4 voxels, two levels above the voxels.
constexpr unsigned kBrickDepth = 14;

// [begin, end) split into runs of equal child index at `depth` (< kBrickDepth), calling
// visit(child, b, e).
template <typename Visit>
void forEachChildRun(unsigned depth, const TouchedBrick* begin, const TouchedBrick* end,
                     Visit visit) {
  const unsigned shift = 3 * (kBrickDepth - 1 - depth);
  for (const TouchedBrick* run = begin; run != end;) {
    const auto child = static_cast<unsigned>((run->code >> shift) & 7);
    const TouchedBrick* run_end = std::find_if(
        run, end, [&](const TouchedBrick& b) { return ((b.code >> shift) & 7) != child; });
    visit(child, run, run_end);
    run = run_end;
  }
}

constexpr uint64_t kAllBits = ~uint64_t{0};
}  // namespace

void BulkOcTree::applyBricks(const std::vector<TouchedBrick>& bricks, unsigned threads,
                             common::WorkerPool* pool, std::vector<VoxelChange>* changes) {
  if (changes != nullptr) changes->clear();
  if (bricks.empty()) return;
  changes_ = changes;
  bool created = false;
  if (root == nullptr) {
    root = new OcTreeNode();  // as updateNode() does for an empty tree
    ++tree_size;
    created = true;
  }
  const Brick* const begin = bricks.data();
  const Brick* const end = begin + bricks.size();
  if (threads < 2) {
    descend(root, created, 0, begin, end);
    changes_ = nullptr;
    return;
  }
  // Top levels serially (create or expand the nodes down to kTaskDepth), the subtrees below
  // on two threads, then the top levels' occupancy and pruning serially on the way back up.
  std::vector<Task> tasks;
  openTop(root, created, 0, begin, end, tasks);
  // The second thread changes nodes through a twin tree with the same sensor model, so that
  // OctoMap's node bookkeeping (tree_size) of the two threads never touches the same counter.
  BulkOcTree twin(getResolution());
  twin.setProbHit(getProbHit());
  twin.setProbMiss(getProbMiss());
  twin.setClampingThresMin(getClampingThresMin());
  twin.setClampingThresMax(getClampingThresMax());
  twin.setOccupancyThres(getOccupancyThres());
  std::vector<VoxelChange> twin_changes;
  if (changes != nullptr) twin.changes_ = &twin_changes;
  std::atomic<size_t> next{0};
  auto work = [&tasks, &next](BulkOcTree& tree) {
    for (size_t i; (i = next.fetch_add(1)) < tasks.size();) {
      const Task& t = tasks[i];
      tree.descend(t.node, t.just_created, kTaskDepth, t.begin, t.end);
    }
  };
  runTwo(
      pool, [&] { work(*this); }, [&] { work(twin); });
  if (changes != nullptr) {
    // Each thread took tasks in ascending order, so each list is sorted: one merge.
    const auto middle = static_cast<std::ptrdiff_t>(changes->size());
    changes->insert(changes->end(), twin_changes.begin(), twin_changes.end());
    std::inplace_merge(changes->begin(), changes->begin() + middle, changes->end(),
                       [](const VoxelChange& a, const VoxelChange& b) { return a.code < b.code; });
  }
  changes_ = nullptr;
  tree_size += twin.tree_size;  // wraps correctly when the twin pruned more than it made
  twin.tree_size = 0;
  size_changed = true;
  closeTop(root, 0, begin, end);
}

void BulkOcTree::openTop(OcTreeNode* node, bool node_just_created, unsigned depth,
                         const Brick* begin, const Brick* end, std::vector<Task>& tasks) {
  if (depth == kTaskDepth) {
    tasks.push_back({node, node_just_created, begin, end});
    return;
  }
  forEachChildRun(depth, begin, end, [&](unsigned child, auto b, auto e) {
    const bool created = openChild(node, node_just_created, child);
    openTop(getNodeChild(node, child), created, depth + 1, b, e, tasks);
  });
}

void BulkOcTree::closeTop(OcTreeNode* node, unsigned depth, const Brick* begin, const Brick* end) {
  if (depth == kTaskDepth) return;
  forEachChildRun(depth, begin, end, [&](unsigned child, auto b, auto e) {
    closeTop(getNodeChild(node, child), depth + 1, b, e);
  });
  close(node);
}

bool BulkOcTree::openChild(OcTreeNode* node, bool node_just_created, unsigned child) {
  if (nodeChildExists(node, child)) return false;
  if (!nodeHasChildren(node) && !node_just_created) {
    expandNode(node);  // a pruned node: give it its eight children back
    return false;
  }
  createNodeChild(node, child);
  return true;
}

void BulkOcTree::close(OcTreeNode* node) {
  if (!pruneNode(node)) node->updateOccupancyChildren();
}

// Mirrors OccupancyOcTreeBase::updateNodeRecurs for all voxels below `node` at once.
void BulkOcTree::descend(OcTreeNode* node, bool node_just_created, unsigned depth,
                         const Brick* begin, const Brick* end) {
  if (depth == kBrickDepth) {
    descendBrick(node, node_just_created, begin->code, begin->any, begin->occupied);
    return;
  }
  // OctoMap's updateNode() leaves a voxel alone when the node holding it (a leaf, or a pruned
  // block) is already clamped in the update's direction. Below a clamped block whose updates
  // are all of that kind nothing can move: expanding it and pruning it back, as the loop
  // below would, is only allocation churn (every frame, in a mature map's saturated space).
  if (!node_just_created && !nodeHasChildren(node)) {
    const bool all_missed = std::all_of(begin, end, [](const Brick& b) { return b.occupied == 0; });
    const bool all_hit =
        std::all_of(begin, end, [](const Brick& b) { return b.occupied == b.any; });
    if (clamped(node, all_missed, all_hit)) return;
  }
  // Every voxel below a childless node gets the same update (common in free space near the
  // sensor): OctoMap would create or expand all the children, update them alike and prune
  // them back into this node. Updating the node itself gives the same tree, without the
  // allocations.
  const auto count = static_cast<size_t>(end - begin);
  if (count == size_t{1} << (3 * (kBrickDepth - depth)) && !nodeHasChildren(node)) {
    const uint64_t flag = begin->occupied;
    if ((flag == 0 || flag == kAllBits) && std::all_of(begin, end, [flag](const Brick& b) {
          return b.any == kAllBits && b.occupied == flag;
        })) {
      updateWhole(node, node_just_created, depth, begin->code << 6, flag != 0);
      return;
    }
  }
  forEachChildRun(depth, begin, end, [&](unsigned child, auto b, auto e) {
    const bool created = openChild(node, node_just_created, child);
    descend(getNodeChild(node, child), created, depth + 1, b, e);
  });
  close(node);
}

// A brick's 64 bits are its voxels in Morton order: bits 8c..8c+7 are the octet of child c.
void BulkOcTree::descendBrick(OcTreeNode* node, bool node_just_created, uint64_t brick_code,
                              uint64_t any, uint64_t occupied) {
  const bool childless = !nodeHasChildren(node);
  if (!node_just_created && childless && clamped(node, occupied == 0, occupied == any)) return;
  if (childless && any == kAllBits && (occupied == 0 || occupied == kAllBits)) {
    updateWhole(node, node_just_created, kBrickDepth, brick_code << 6, occupied != 0);
    return;
  }
  for (unsigned child = 0; child < 8; ++child) {
    const auto octet_any = static_cast<unsigned>((any >> (8 * child)) & 0xFF);
    if (octet_any == 0) continue;
    const bool created = openChild(node, node_just_created, child);
    descendOctet(getNodeChild(node, child), created, brick_code << 6 | 8 * child, octet_any,
                 static_cast<unsigned>((occupied >> (8 * child)) & 0xFF));
  }
  close(node);
}

void BulkOcTree::descendOctet(OcTreeNode* node, bool node_just_created, uint64_t first_voxel,
                              unsigned any, unsigned occupied) {
  const bool childless = !nodeHasChildren(node);
  if (!node_just_created && childless && clamped(node, occupied == 0, occupied == any)) return;
  if (childless && any == 0xFF && (occupied == 0 || occupied == 0xFF)) {
    updateWhole(node, node_just_created, kBrickDepth + 1, first_voxel, occupied != 0);
    return;
  }
  for (unsigned bits = any; bits != 0; bits &= bits - 1) {
    const auto child = static_cast<unsigned>(__builtin_ctz(bits));
    const bool created = openChild(node, node_just_created, child);
    OcTreeNode* voxel = getNodeChild(node, child);
    // Each voxel gets one hit or one miss, clamped as updateNode() does.
    const float before = voxel->getLogOdds();
    updateNodeLogOdds(voxel, ((occupied >> child) & 1) ? prob_hit_log : prob_miss_log);
    if (changes_ != nullptr) {
      noteChange(first_voxel | child, tree_depth, created, before, voxel->getLogOdds());
    }
  }
  close(node);
}

void BulkOcTree::updateWhole(OcTreeNode* node, bool node_just_created, unsigned depth,
                             uint64_t first_voxel, bool occupied) {
  const float before = node->getLogOdds();
  updateNodeLogOdds(node, occupied ? prob_hit_log : prob_miss_log);
  if (changes_ != nullptr) {
    noteChange(first_voxel, depth, node_just_created, before, node->getLogOdds());
  }
}

bool BulkOcTree::clamped(const OcTreeNode* node, bool all_missed, bool all_hit) const {
  const float log_odds = node->getLogOdds();
  return (log_odds <= clamping_thres_min && all_missed) ||
         (log_odds >= clamping_thres_max && all_hit);
}

void BulkOcTree::noteChange(uint64_t code, unsigned depth, bool just_created, float before,
                            float after) {
  // A node made just now was unknown before, whatever value it was created with.
  const bool was_occupied = !just_created && before >= occ_prob_thres_log;
  const bool occupied = after >= occ_prob_thres_log;
  if (!was_occupied && !occupied) return;  // free or unknown: nobody draws it
  if (was_occupied && occupied && before == after) return;
  const uint8_t value = occupied ? occupancyByte(after) : 0;
  if (was_occupied && occupied && occupancyByte(before) == value) return;
  changes_->push_back({code, static_cast<uint8_t>(depth), value, occupied});
}

void BulkInserter::insert(BulkOcTree& tree, const std::vector<point3d>& points,
                          const point3d& origin, double max_range, unsigned threads,
                          common::WorkerPool* pool, std::vector<VoxelChange>* changes) {
  threads = std::clamp(threads, 1u, 2u);
  if (changes != nullptr) changes->clear();
  OcTreeKey origin_key;
  if (!tree.coordToKeyChecked(origin, origin_key)) return;
  // Each step runs on both threads, each on its share: the points' halves, then the box's.
  auto onEach = [&](const std::function<void(unsigned t)>& step) {
    if (threads == 2) {
      runTwo(
          pool, [&] { step(0); }, [&] { step(1); });
    } else {
      step(0);
    }
  };
  auto share = [&](unsigned t, size_t n) {
    return std::pair{n * t / threads, n * (t + 1) / threads};
  };
  // Ray ends: measured points, or the point at max_range along a longer ray (free only); and
  // the keys they span.
  ends_.resize(points.size());
  hit_.resize(points.size());
  std::array<std::array<int, 3>, 2> lo{}, hi{};
  onEach([&](unsigned t) {
    lo[t] = {origin_key[0], origin_key[1], origin_key[2]};
    hi[t] = lo[t];
    const auto [from, to] = share(t, points.size());
    OcTreeKey key;
    for (size_t i = from; i < to; ++i) {
      const point3d& p = points[i];
      hit_[i] = max_range < 0.0 || (p - origin).norm() <= max_range;
      ends_[i] = hit_[i] ? p : origin + (p - origin).normalized() * static_cast<float>(max_range);
      if (!tree.coordToKeyChecked(ends_[i], key)) continue;
      for (int a = 0; a < 3; ++a) {
        lo[t][a] = std::min<int>(lo[t][a], key[a]);
        hi[t][a] = std::max<int>(hi[t][a], key[a]);
      }
    }
  });
  // One voxel of margin on every side: a ray's walk can step one voxel past its end voxel
  // (the voxel's exit is compared with the ray's length in floating point, by OctoMap too,
  // which marks that voxel free as well). Found as a write before the buffer by ASan.
  for (int a = 0; a < 3; ++a) {
    lo[0][a] = std::max(std::min(lo[0][a], lo[threads - 1][a]) - 1, 0);
    hi[0][a] = std::min(std::max(hi[0][a], hi[threads - 1][a]) + 1, 0xFFFF);
  }
  const VoxelBox box = VoxelBox::around(lo[0], hi[0]);
  // Each thread marks its rays' voxels in bitsets of its own: free ones, and the hits.
  onEach([&](unsigned t) {
    free_bits_[t].assign(box.words(), 0);
    occupied_bits_[t].assign(box.words(), 0);
    const auto [from, to] = share(t, points.size());
    castRays(tree, origin, ends_, from, to, box, free_bits_[t].data());
    OcTreeKey key;
    for (size_t i = from; i < to; ++i) {
      if (hit_[i] && tree.coordToKeyChecked(ends_[i], key)) {
        markVoxel(occupied_bits_[t].data(), box, key[0] - box.min[0], key[1] - box.min[1],
                  key[2] - box.min[2]);
      }
    }
  });
  // The touched bricks, each thread a share of the box.
  std::vector<const uint64_t*> free_sets, occupied_sets;
  for (unsigned t = 0; t < threads; ++t) {
    free_sets.push_back(free_bits_[t].data());
    occupied_sets.push_back(occupied_bits_[t].data());
  }
  onEach([&](unsigned t) {
    const auto [from, to] = share(t, static_cast<size_t>(box.size[0] / 4));
    collectBricks(box, free_sets, occupied_sets, static_cast<int>(from), static_cast<int>(to),
                  bricks_[t]);
  });
  if (threads == 2) bricks_[0].insert(bricks_[0].end(), bricks_[1].begin(), bricks_[1].end());
  const std::vector<TouchedBrick>& bricks = bricks_[0];

  // Sorted by Morton code (the brick's code above its place in `bricks`).
  constexpr unsigned kIndexBits = 22;
  order_.clear();
  if (bricks.size() < (size_t{1} << kIndexBits)) {
    for (size_t i = 0; i < bricks.size(); ++i) order_.push_back(bricks[i].code << kIndexBits | i);
    radixSort(order_, scratch_, counts_, 64);
    for (uint64_t& entry : order_) entry &= (uint64_t{1} << kIndexBits) - 1;
  } else {  // more than 4M bricks touched (256M voxels): rare, sort the slow way
    for (size_t i = 0; i < bricks.size(); ++i) order_.push_back(i);
    std::sort(order_.begin(), order_.end(),
              [&](uint64_t a, uint64_t b) { return bricks[a].code < bricks[b].code; });
  }
  // Occupied wins over free (as OctoMap's computeUpdate): a brick's `occupied` marks its hits.
  sorted_.clear();
  for (const uint64_t i : order_) sorted_.push_back(bricks[i]);
  tree.applyBricks(sorted_, threads, pool, changes);
}

}  // namespace stereomap::fusion::detail
