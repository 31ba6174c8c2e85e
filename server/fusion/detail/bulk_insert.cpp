#include "server/fusion/detail/bulk_insert.hpp"

#include <algorithm>
#include <array>
#include <atomic>
#include <cassert>
#include <cmath>
#include <limits>

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

// The voxels an update can touch, as bricks of 4x4x4 voxels: one 64-bit word per brick,
// whose bits are the brick's voxels in Morton order. The box starts on a multiple of 4, so
// a voxel's Morton code is its brick's code followed by its bit: listing the bricks in
// Morton order lists the voxels in Morton order (only bricks need sorting, not voxels).
struct BrickBox {
  std::array<int, 3> min{};     // first key of the box (a multiple of 4 on each axis)
  std::array<int, 3> bricks{};  // bricks along each axis
  size_t words() const { return static_cast<size_t>(bricks[0]) * bricks[1] * bricks[2]; }
  size_t brickIndex(int rx, int ry, int rz) const {  // relative keys
    return (static_cast<size_t>(rx >> 2) * bricks[1] + (ry >> 2)) * bricks[2] + (rz >> 2);
  }
  std::array<int, 3> brickKey(size_t word) const {  // absolute key of the brick's corner
    const int bz = static_cast<int>(word % bricks[2]);
    word /= bricks[2];
    const int by = static_cast<int>(word % bricks[1]);
    const int bx = static_cast<int>(word / bricks[1]);
    return {min[0] + 4 * bx, min[1] + 4 * by, min[2] + 4 * bz};
  }
};

// Bit of a voxel inside its brick: the Morton code of its 2-bit coordinates.
constexpr std::array<uint8_t, 64> kBrickBit = [] {
  std::array<uint8_t, 64> bit{};
  for (unsigned i = 0; i < 64; ++i) {
    const unsigned x = i & 3, y = (i >> 2) & 3, z = (i >> 4) & 3;
    bit[i] = static_cast<uint8_t>((x & 1) | (y & 1) << 1 | (z & 1) << 2 | (x >> 1) << 3 |
                                  (y >> 1) << 4 | (z >> 1) << 5);
  }
  return bit;
}();

inline void markVoxel(std::vector<uint64_t>& words, const BrickBox& box, int rx, int ry, int rz) {
  words[box.brickIndex(rx, ry, rz)] |= uint64_t{1}
                                       << kBrickBit[(rx & 3) | (ry & 3) << 2 | (rz & 3) << 4];
}

// One ray of OctoMap's computeRayKeys (Amanatides & Woo), with the same float/double
// arithmetic so that it visits the same voxels, as a walk over bit indices of a KeyBox.
class RayWalk {
 public:
  // Prepares the walk from `origin` to `end` and returns the origin voxel's bit, or false
  // when there is nothing to mark (an end outside the tree, or origin and end in one voxel).
  bool start(const octomap::OcTree& tree, const point3d& origin, const point3d& end,
             const BrickBox& box) {
    OcTreeKey key_origin, key_end;
    if (!tree.coordToKeyChecked(origin, key_origin) || !tree.coordToKeyChecked(end, key_end)) {
      return false;
    }
    if (key_origin == key_end) return false;
    point3d direction = end - origin;
    length_ = static_cast<float>(direction.norm());
    // A ray whose length underflows float (an end 1e-38 m from an origin on a voxel border,
    // in another voxel) has no direction: its walk would never end. Found by fuzzing
    // (tests/fuzz/corpus/samples/ray-without-length), as a write past the box.
    if (!(length_ > 0) || !std::isfinite(length_)) return false;
    direction /= length_;
    const double resolution = tree.getResolution();
    double t_max[3], t_delta[3];
    for (unsigned i = 0; i < 3; ++i) {
      step_[i] = direction(i) > 0.0 ? 1 : direction(i) < 0.0 ? -1 : 0;
      if (step_[i] != 0) {
        double border = tree.keyToCoord(key_origin[i]);
        border += static_cast<float>(step_[i] * resolution * 0.5);
        t_max[i] = (border - origin(i)) / direction(i);
        t_delta[i] = resolution / std::fabs(direction(i));
      } else {
        t_max[i] = t_delta[i] = std::numeric_limits<double>::max();
      }
      key_[i] = key_origin[i] - box.min[i];  // relative to the box from here on
      end_[i] = key_end[i] - box.min[i];
    }
    for (unsigned i = 0; i < 3; ++i) limit_[i] = 4 * static_cast<unsigned>(box.bricks[i]);
    stride_x_ = static_cast<size_t>(box.bricks[1]) * box.bricks[2];
    stride_y_ = static_cast<size_t>(box.bricks[2]);
    t0_ = t_max[0], t1_ = t_max[1], t2_ = t_max[2];
    d0_ = t_delta[0], d1_ = t_delta[1], d2_ = t_delta[2];
    return true;
  }

  // One voxel further; false when the ray is done, else key() is the voxel to mark. The
  // next axis is the smallest t_max, ties going to the later axis (as OctoMap), chosen with
  // selects instead of branches: the choice is unpredictable, and a mispredicted branch per
  // voxel was most of the cost.
  bool advance() {
    const bool x_first = t0_ < t1_;
    const bool z_next = !((x_first ? t0_ : t1_) < t2_);
    const bool x_next = x_first && !z_next;
    const bool y_next = !x_first && !z_next;
    key_[0] += x_next ? step_[0] : 0;
    key_[1] += y_next ? step_[1] : 0;
    key_[2] += z_next ? step_[2] : 0;
    t0_ += x_next ? d0_ : 0.0;
    t1_ += y_next ? d1_ : 0.0;
    t2_ += z_next ? d2_ : 0.0;
    if (key_[0] == end_[0] && key_[1] == end_[1] && key_[2] == end_[2]) return false;
    return !(std::min(std::min(t0_, t1_), t2_) > length_);
  }
  // Why a walk stays inside the box with its margin of one voxel (asserted in debug builds
  // only, the walk being the hot loop; AddressSanitizer sees any write outside): a voxel is entered
  // only while the ray's parameter is within its length, so every voxel walked touches the segment
  // up to rounding; coordinates are floats over a tree of 2^16 voxels a side, so rounding is below
  // 1/256 of a voxel, and a walk can end at most one voxel outside the segment's voxels.
  void mark(uint64_t* words) const {
    assert(static_cast<unsigned>(key_[0]) < limit_[0] &&
           static_cast<unsigned>(key_[1]) < limit_[1] &&
           static_cast<unsigned>(key_[2]) < limit_[2]);
    const size_t word = static_cast<size_t>(key_[0] >> 2) * stride_x_ +
                        static_cast<size_t>(key_[1] >> 2) * stride_y_ +
                        static_cast<size_t>(key_[2] >> 2);
    words[word] |=
        uint64_t{1} << kBrickBit[(key_[0] & 3) | (key_[1] & 3) << 2 | (key_[2] & 3) << 4];
  }

 private:
  double t0_, t1_, t2_, d0_, d1_, d2_;
  int key_[3], end_[3], step_[3];
  unsigned limit_[3];  // keys (relative to the box) at or beyond these are outside it
  size_t stride_x_, stride_y_;
  float length_;
};

// Marks the voxels of the rays origin -> ends[from..to). Two rays are walked in turns:
// each walk is one long chain of dependent steps, and two of them keep the core busier.
void castRays(const octomap::OcTree& tree, const point3d& origin, const std::vector<point3d>& ends,
              size_t from, size_t to, const BrickBox& box, std::vector<uint64_t>& bit_words) {
  uint64_t* const bits = bit_words.data();  // a plain pointer: the loop keeps it in a register
  size_t next = from;
  auto load = [&](RayWalk& walk) {
    while (next < to) {
      if (walk.start(tree, origin, ends[next++], box)) {
        walk.mark(bits);  // the origin's voxel
        return true;
      }
    }
    return false;
  };
  RayWalk a, b;
  bool a_live = load(a), b_live = load(b);
  while (a_live && b_live) {
    if (a.advance()) {
      a.mark(bits);
    } else {
      a_live = load(a);
    }
    if (b.advance()) {
      b.mark(bits);
    } else {
      b_live = load(b);
    }
  }
  for (RayWalk* walk : {&a, &b}) {
    for (bool live = walk == &a ? a_live : b_live; live;) {
      if (walk->advance()) {
        walk->mark(bits);
      } else {
        live = load(*walk);
      }
    }
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
  BrickBox box;
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
    box.min[a] = std::max(lo[a] - 1, 0) & ~3;
    box.bricks[a] = (std::min(hi[a] + 1, 0xFFFF) - box.min[a]) / 4 + 1;
  }
  const size_t words = box.words();
  for (unsigned t = 0; t < threads; ++t) free_bits_[t].assign(words, 0);
  occupied_bits_.assign(words, 0);

  auto castRange = [&](unsigned t, size_t from, size_t to) {
    castRays(tree, origin, ends, from, to, box, free_bits_[t]);
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
      markVoxel(occupied_bits_, box, key[0] - box.min[0], key[1] - box.min[1], key[2] - box.min[2]);
    }
  }

  // The touched bricks, sorted by Morton code (the brick's code above its word index).
  constexpr unsigned kIndexBits = 22;
  bricks_.clear();
  for (size_t w = 0; w < words; ++w) {
    uint64_t any = free_bits_[0][w] | occupied_bits_[w];
    if (threads == 2) any |= free_bits_[1][w];
    if (any == 0) continue;
    const auto corner = box.brickKey(w);
    const OcTreeKey brick(static_cast<uint16_t>(corner[0] >> 2),
                          static_cast<uint16_t>(corner[1] >> 2),
                          static_cast<uint16_t>(corner[2] >> 2));
    bricks_.push_back(mortonCode(brick) << kIndexBits | w);
  }
  const bool fits = words < (size_t{1} << kIndexBits);
  if (fits) {
    radixSort(bricks_, scratch_, counts_, 64);
  } else {  // a box of more than 4M bricks (256M voxels): rare, sort the slow way
    std::vector<std::pair<uint64_t, size_t>> order;
    for (size_t w = 0; w < words; ++w) {
      uint64_t any = free_bits_[0][w] | occupied_bits_[w];
      if (threads == 2) any |= free_bits_[1][w];
      if (any == 0) continue;
      const auto corner = box.brickKey(w);
      order.emplace_back(mortonCode(OcTreeKey(static_cast<uint16_t>(corner[0] >> 2),
                                              static_cast<uint16_t>(corner[1] >> 2),
                                              static_cast<uint16_t>(corner[2] >> 2))),
                         w);
    }
    std::sort(order.begin(), order.end());
    bricks_.clear();
    for (const auto& [code, w] : order) bricks_.push_back(code << kIndexBits | w);
  }
  // Occupied wins over free (as OctoMap's computeUpdate). Each brick's voxels come out in
  // Morton order as its bits do; the code of a voxel is its brick's code and its bit.
  codes_.clear();
  for (const uint64_t entry : bricks_) {
    const size_t w = entry & ((uint64_t{1} << kIndexBits) - 1);
    const uint64_t brick_code = fits ? entry >> kIndexBits : 0;
    const uint64_t occupied = occupied_bits_[w];
    uint64_t any = free_bits_[0][w] | occupied;
    if (threads == 2) any |= free_bits_[1][w];
    const uint64_t base = (fits ? brick_code : (entry >> kIndexBits)) << 6;
    while (any != 0) {
      const unsigned bit = static_cast<unsigned>(__builtin_ctzll(any));
      any &= any - 1;
      codes_.push_back((base | bit) << 1 | ((occupied >> bit) & 1));
    }
  }
  tree.applySortedUpdates(codes_, threads, pool, changes);
}

}  // namespace stereomap::fusion::detail
