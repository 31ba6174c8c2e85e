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

// LSD radix sort of 64-bit values whose set bits are below `bits`. (Splitting it over two
// threads measured no faster: it is memory-bound.)
void radixSort(std::vector<uint64_t>& values, std::vector<uint64_t>& scratch,
               std::vector<uint32_t>& counts, unsigned bits) {
  constexpr unsigned kDigit = 16;
  scratch.resize(values.size());
  counts.resize(size_t{1} << kDigit);
  for (unsigned shift = 0; shift < bits; shift += kDigit) {
    std::fill(counts.begin(), counts.end(), 0);
    for (uint64_t v : values) ++counts[(v >> shift) & 0xFFFF];
    uint32_t sum = 0;
    for (auto& c : counts) {
      const uint32_t n = c;
      c = sum;
      sum += n;
    }
    for (uint64_t v : values) scratch[counts[(v >> shift) & 0xFFFF]++] = v;
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

uint64_t mortonCode(const OcTreeKey& key) { return mortonOfKeys(key[0], key[1], key[2]); }

OcTreeKey mortonDecode(uint64_t code) {
  return OcTreeKey(static_cast<uint16_t>(fusion::detail::compactBits(code)),
                   static_cast<uint16_t>(fusion::detail::compactBits(code >> 1)),
                   static_cast<uint16_t>(fusion::detail::compactBits(code >> 2)));
}

namespace {
// Subtrees at this depth are the units of parallel work (up to 512 of them).
constexpr unsigned kTaskDepth = 3;

// [begin, end) split into runs of equal child index at `depth`, calling visit(child, b, e).
template <typename Visit>
void forEachChildRun(unsigned tree_depth, unsigned depth, const uint64_t* begin,
                     const uint64_t* end, Visit visit) {
  const unsigned shift = 3 * (tree_depth - 1 - depth) + 1;  // above the occupied flag
  for (const uint64_t* run = begin; run != end;) {
    const unsigned child = static_cast<unsigned>((*run >> shift) & 7);
    const uint64_t* run_end =
        std::find_if(run, end, [&](uint64_t c) { return ((c >> shift) & 7) != child; });
    visit(child, run, run_end);
    run = run_end;
  }
}
}  // namespace

void BulkOcTree::applySortedUpdates(const std::vector<uint64_t>& codes, unsigned threads,
                                    common::WorkerPool* pool, std::vector<VoxelChange>* changes) {
  if (changes != nullptr) changes->clear();
  if (codes.empty()) return;
  changes_ = changes;
  bool created = false;
  if (root == nullptr) {
    root = new OcTreeNode();  // as updateNode() does for an empty tree
    ++tree_size;
    created = true;
  }
  if (threads < 2) {
    descend(root, created, 0, codes.data(), codes.data() + codes.size());
    changes_ = nullptr;
    return;
  }
  // Top levels serially (create or expand the nodes down to kTaskDepth), the subtrees below
  // on two threads, then the top levels' occupancy and pruning serially on the way back up.
  std::vector<Task> tasks;
  openTop(root, created, 0, codes.data(), codes.data() + codes.size(), tasks);
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
  closeTop(root, 0, codes.data(), codes.data() + codes.size());
}

void BulkOcTree::openTop(OcTreeNode* node, bool node_just_created, unsigned depth,
                         const uint64_t* begin, const uint64_t* end, std::vector<Task>& tasks) {
  if (depth == kTaskDepth) {
    tasks.push_back({node, node_just_created, begin, end});
    return;
  }
  forEachChildRun(tree_depth, depth, begin, end, [&](unsigned child, auto b, auto e) {
    const bool created = openChild(node, node_just_created, child);
    openTop(getNodeChild(node, child), created, depth + 1, b, e, tasks);
  });
}

void BulkOcTree::closeTop(OcTreeNode* node, unsigned depth, const uint64_t* begin,
                          const uint64_t* end) {
  if (depth == kTaskDepth) return;
  forEachChildRun(tree_depth, depth, begin, end, [&](unsigned child, auto b, auto e) {
    closeTop(getNodeChild(node, child), depth + 1, b, e);
  });
  if (!pruneNode(node)) node->updateOccupancyChildren();
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

// Mirrors OccupancyOcTreeBase::updateNodeRecurs for all keys below `node` at once.
void BulkOcTree::descend(OcTreeNode* node, bool node_just_created, unsigned depth,
                         const uint64_t* begin, const uint64_t* end) {
  // OctoMap's updateNode() leaves a voxel alone when the node holding it (a leaf, or a pruned
  // block) is already clamped in the update's direction. Below a clamped block whose updates
  // are all of that kind nothing can move: expanding it and pruning it back, as the loop
  // below would, is only allocation churn (every frame, in a mature map's saturated space).
  if (!node_just_created && !nodeHasChildren(node) && clampedForAll(node, begin, end)) return;
  if (depth == tree_depth) {
    // Each key appears once: one hit or one miss, clamped as updateNode() does.
    const float before = node->getLogOdds();
    updateNodeLogOdds(node, (*begin & 1) ? prob_hit_log : prob_miss_log);
    if (changes_ != nullptr) {
      noteChange(*begin >> 1, depth, node_just_created, before, node->getLogOdds());
    }
    return;
  }
  // Every voxel below a childless node gets the same update (common in free space near the
  // sensor): OctoMap would create or expand all the children, update them alike and prune
  // them back into this node. Updating the node itself gives the same tree, without the
  // allocations.
  const auto count = static_cast<size_t>(end - begin);
  if (count == size_t{1} << (3 * (tree_depth - depth)) && !nodeHasChildren(node)) {
    const uint64_t flag = *begin & 1;
    if (std::all_of(begin, end, [flag](uint64_t c) { return (c & 1) == flag; })) {
      const float before = node->getLogOdds();
      updateNodeLogOdds(node, flag ? prob_hit_log : prob_miss_log);
      if (changes_ != nullptr) {
        noteChange(*begin >> 1, depth, node_just_created, before, node->getLogOdds());
      }
      return;
    }
  }
  forEachChildRun(tree_depth, depth, begin, end, [&](unsigned child, auto b, auto e) {
    const bool created = openChild(node, node_just_created, child);
    descend(getNodeChild(node, child), created, depth + 1, b, e);
  });
  if (!pruneNode(node)) node->updateOccupancyChildren();
}

bool BulkOcTree::clampedForAll(const OcTreeNode* node, const uint64_t* begin,
                               const uint64_t* end) const {
  const float log_odds = node->getLogOdds();
  if (log_odds <= clamping_thres_min) {
    return std::none_of(begin, end, [](uint64_t c) { return (c & 1) != 0; });
  }
  if (log_odds >= clamping_thres_max) {
    return std::all_of(begin, end, [](uint64_t c) { return (c & 1) != 0; });
  }
  return false;
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
  // Ray ends: measured points, or the point at max_range along a longer ray (free only).
  std::vector<point3d> ends(points.size());
  std::vector<uint8_t> hit(points.size());
  OcTreeKey key;
  if (changes != nullptr) changes->clear();
  if (!tree.coordToKeyChecked(origin, key)) return;
  std::array<int, 3> lo{key[0], key[1], key[2]}, hi = lo;
  for (size_t i = 0; i < points.size(); ++i) {
    const point3d& p = points[i];
    hit[i] = max_range < 0.0 || (p - origin).norm() <= max_range;
    ends[i] = hit[i] ? p : origin + (p - origin).normalized() * static_cast<float>(max_range);
    if (!tree.coordToKeyChecked(ends[i], key)) continue;
    for (int a = 0; a < 3; ++a) {
      lo[a] = std::min<int>(lo[a], key[a]);
      hi[a] = std::max<int>(hi[a], key[a]);
    }
  }
  // One voxel of margin on every side: a ray's walk can step one voxel past its end voxel
  // (the voxel's exit is compared with the ray's length in floating point, by OctoMap too,
  // which marks that voxel free as well). Found as a write before the buffer by ASan.
  for (int a = 0; a < 3; ++a) {
    lo[a] = std::max(lo[a] - 1, 0);
    hi[a] = std::min(hi[a] + 1, 0xFFFF);
  }
  const VoxelBox box = VoxelBox::around(lo, hi);
  const size_t words = box.words();
  for (unsigned t = 0; t < threads; ++t) free_bits_[t].assign(words, 0);
  occupied_bits_.assign(words, 0);

  auto castRange = [&](unsigned t, size_t from, size_t to) {
    castRays(tree, origin, ends, from, to, box, free_bits_[t].data());
  };
  if (threads == 2) {
    runTwo(
        pool, [&] { castRange(0, 0, points.size() / 2); },
        [&] { castRange(1, points.size() / 2, points.size()); });
  } else {
    castRange(0, 0, points.size());
  }
  for (size_t i = 0; i < points.size(); ++i) {
    if (hit[i] && tree.coordToKeyChecked(ends[i], key)) {
      markVoxel(occupied_bits_.data(), box, key[0] - box.min[0], key[1] - box.min[1],
                key[2] - box.min[2]);
    }
  }

  // The touched bricks, sorted by Morton code (the brick's code above its place in bricks_).
  std::vector<const uint64_t*> free_sets{free_bits_[0].data()};
  if (threads == 2) free_sets.push_back(free_bits_[1].data());
  collectBricks(box, free_sets, occupied_bits_.data(), bricks_);
  constexpr unsigned kIndexBits = 22;
  order_.clear();
  if (bricks_.size() < (size_t{1} << kIndexBits)) {
    for (size_t i = 0; i < bricks_.size(); ++i) order_.push_back(bricks_[i].code << kIndexBits | i);
    radixSort(order_, scratch_, counts_, 64);
    for (uint64_t& entry : order_) entry &= (uint64_t{1} << kIndexBits) - 1;
  } else {  // more than 4M bricks touched (256M voxels): rare, sort the slow way
    for (size_t i = 0; i < bricks_.size(); ++i) order_.push_back(i);
    std::sort(order_.begin(), order_.end(),
              [&](uint64_t a, uint64_t b) { return bricks_[a].code < bricks_[b].code; });
  }
  // Occupied wins over free (as OctoMap's computeUpdate). Each brick's voxels come out in
  // Morton order as its bits do; the code of a voxel is its brick's code and its bit.
  codes_.clear();
  for (const uint64_t i : order_) {
    const TouchedBrick& brick = bricks_[i];
    const uint64_t base = brick.code << 6;
    for (uint64_t any = brick.any; any != 0; any &= any - 1) {
      const unsigned bit = static_cast<unsigned>(__builtin_ctzll(any));
      codes_.push_back((base | bit) << 1 | ((brick.occupied >> bit) & 1));
    }
  }
  tree.applySortedUpdates(codes_, threads, pool, changes);
}

}  // namespace stereomap::fusion::detail
