#include "server/fusion/detail/bulk_insert.hpp"

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <limits>
#include <thread>

namespace stereomap::fusion::detail {

using octomap::OcTreeKey;
using octomap::OcTreeNode;
using octomap::point3d;

namespace {

uint64_t spreadBits(uint64_t v) {  // 16 bits -> every third bit
  v &= 0xFFFF;
  v = (v | v << 32) & 0x1F00000000FFFFull;
  v = (v | v << 16) & 0x1F0000FF0000FFull;
  v = (v | v << 8) & 0x100F00F00F00F00Full;
  v = (v | v << 4) & 0x10C30C30C30C30C3ull;
  v = (v | v << 2) & 0x1249249249249249ull;
  return v;
}

uint64_t compactBits(uint64_t v) {
  v &= 0x1249249249249249ull;
  v = (v ^ (v >> 2)) & 0x10C30C30C30C30C3ull;
  v = (v ^ (v >> 4)) & 0x100F00F00F00F00Full;
  v = (v ^ (v >> 8)) & 0x1F0000FF0000FFull;
  v = (v ^ (v >> 16)) & 0x1F00000000FFFFull;
  v = (v ^ (v >> 32)) & 0x1FFFFFull;
  return v;
}

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

// The key box that holds every voxel of the update, and the bit index of a key in it.
struct KeyBox {
  std::array<int, 3> min{}, size{};
  size_t bits() const { return static_cast<size_t>(size[0]) * size[1] * size[2]; }
  size_t index(const OcTreeKey& k) const {
    return (static_cast<size_t>(k[0] - min[0]) * size[1] + (k[1] - min[1])) * size[2] +
           (k[2] - min[2]);
  }
  OcTreeKey key(size_t index) const {
    const int z = static_cast<int>(index % size[2]);
    index /= size[2];
    const int y = static_cast<int>(index % size[1]);
    const int x = static_cast<int>(index / size[1]);
    return OcTreeKey(static_cast<uint16_t>(x + min[0]), static_cast<uint16_t>(y + min[1]),
                     static_cast<uint16_t>(z + min[2]));
  }
};

inline void setBit(std::vector<uint64_t>& bits, size_t index) {
  bits[index >> 6] |= uint64_t{1} << (index & 63);
}

// OctoMap's computeRayKeys (Amanatides & Woo), with the same float/double arithmetic so
// that it visits the same voxels, writing into a bitset instead of a KeyRay. The loop is
// arranged so that each step finds the next axis once and moves the bit index by a stride.
void castRay(const octomap::OcTree& tree, const point3d& origin, const point3d& end,
             const KeyBox& box, std::vector<uint64_t>& bits) {
  OcTreeKey key_origin, key_end;
  if (!tree.coordToKeyChecked(origin, key_origin) || !tree.coordToKeyChecked(end, key_end)) return;
  if (key_origin == key_end) return;
  size_t index = box.index(key_origin);
  setBit(bits, index);

  point3d direction = end - origin;
  const float length = static_cast<float>(direction.norm());
  direction /= length;
  const double resolution = tree.getResolution();
  const int64_t stride[3] = {static_cast<int64_t>(box.size[1]) * box.size[2], box.size[2], 1};
  int step[3];
  int64_t index_step[3];
  double t_max[3], t_delta[3];
  OcTreeKey current = key_origin;
  for (unsigned i = 0; i < 3; ++i) {
    step[i] = direction(i) > 0.0 ? 1 : direction(i) < 0.0 ? -1 : 0;
    index_step[i] = step[i] * stride[i];
    if (step[i] != 0) {
      double border = tree.keyToCoord(current[i]);
      border += static_cast<float>(step[i] * resolution * 0.5);
      t_max[i] = (border - origin(i)) / direction(i);
      t_delta[i] = resolution / std::fabs(direction(i));
    } else {
      t_max[i] = t_delta[i] = std::numeric_limits<double>::max();
    }
  }
  // The stepping loop below is OctoMap's (the next axis is the smallest t_max, ties going to
  // the later axis) in scalars and selects instead of branches: which axis comes next is
  // unpredictable, and a mispredicted branch per voxel was most of the cost.
  double t0 = t_max[0], t1 = t_max[1], t2 = t_max[2];
  const double d0 = t_delta[0], d1 = t_delta[1], d2 = t_delta[2];
  int k0 = current[0], k1 = current[1], k2 = current[2];
  const int e0 = key_end[0], e1 = key_end[1], e2 = key_end[2];
  for (;;) {
    const bool x_first = t0 < t1;
    const bool z_next = !((x_first ? t0 : t1) < t2);
    const bool x_next = x_first && !z_next;
    const bool y_next = !x_first && !z_next;
    k0 += x_next ? step[0] : 0;
    k1 += y_next ? step[1] : 0;
    k2 += z_next ? step[2] : 0;
    t0 += x_next ? d0 : 0.0;
    t1 += y_next ? d1 : 0.0;
    t2 += z_next ? d2 : 0.0;
    index += x_next ? index_step[0] : y_next ? index_step[1] : index_step[2];
    if (k0 == e0 && k1 == e1 && k2 == e2) return;
    if (std::min(std::min(t0, t1), t2) > length) return;
    setBit(bits, index);
  }
}

}  // namespace

uint64_t mortonCode(const OcTreeKey& key) {
  return spreadBits(key[0]) | spreadBits(key[1]) << 1 | spreadBits(key[2]) << 2;
}

OcTreeKey mortonDecode(uint64_t code) {
  return OcTreeKey(static_cast<uint16_t>(compactBits(code)),
                   static_cast<uint16_t>(compactBits(code >> 1)),
                   static_cast<uint16_t>(compactBits(code >> 2)));
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

void BulkOcTree::applySortedUpdates(const std::vector<uint64_t>& codes, unsigned threads) {
  if (codes.empty()) return;
  bool created = false;
  if (root == nullptr) {
    root = new OcTreeNode();  // as updateNode() does for an empty tree
    ++tree_size;
    created = true;
  }
  if (threads < 2) {
    descend(root, created, 0, codes.data(), codes.data() + codes.size());
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
  std::atomic<size_t> next{0};
  auto work = [&tasks, &next](BulkOcTree& tree) {
    for (size_t i; (i = next.fetch_add(1)) < tasks.size();) {
      const Task& t = tasks[i];
      tree.descend(t.node, t.just_created, kTaskDepth, t.begin, t.end);
    }
  };
  std::thread helper(work, std::ref(twin));
  work(*this);
  helper.join();
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
  if (depth == tree_depth) {
    // Each key appears once: one hit or one miss, clamped as updateNode() does.
    updateNodeLogOdds(node, (*begin & 1) ? prob_hit_log : prob_miss_log);
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
      updateNodeLogOdds(node, flag ? prob_hit_log : prob_miss_log);
      return;
    }
  }
  forEachChildRun(tree_depth, depth, begin, end, [&](unsigned child, auto b, auto e) {
    const bool created = openChild(node, node_just_created, child);
    descend(getNodeChild(node, child), created, depth + 1, b, e);
  });
  if (!pruneNode(node)) node->updateOccupancyChildren();
}

void BulkInserter::insert(BulkOcTree& tree, const std::vector<point3d>& points,
                          const point3d& origin, double max_range, unsigned threads) {
  threads = std::clamp(threads, 1u, 2u);
  // Ray ends: measured points, or the point at max_range along a longer ray (free only).
  std::vector<point3d> ends(points.size());
  std::vector<uint8_t> hit(points.size());
  KeyBox box;
  OcTreeKey key;
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
  for (int a = 0; a < 3; ++a) {
    box.min[a] = lo[a];
    box.size[a] = hi[a] - lo[a] + 1;
  }
  const size_t words = (box.bits() + 63) / 64;
  for (unsigned t = 0; t < threads; ++t) free_bits_[t].assign(words, 0);
  occupied_bits_.assign(words, 0);

  auto castRange = [&](unsigned t, size_t from, size_t to) {
    for (size_t i = from; i < to; ++i) castRay(tree, origin, ends[i], box, free_bits_[t]);
  };
  if (threads == 2) {
    std::thread helper(castRange, 1u, points.size() / 2, points.size());
    castRange(0, 0, points.size() / 2);
    helper.join();
  } else {
    castRange(0, 0, points.size());
  }
  for (size_t i = 0; i < points.size(); ++i) {
    if (hit[i] && tree.coordToKeyChecked(ends[i], key)) setBit(occupied_bits_, box.index(key));
  }

  // Occupied wins over free (as OctoMap's computeUpdate); list both in Morton order.
  auto extract = [&](size_t from, size_t to, std::vector<uint64_t>& out) {
    out.clear();
    for (size_t w = from; w < to; ++w) {
      const uint64_t occupied = occupied_bits_[w];
      uint64_t any = free_bits_[0][w] | occupied;
      if (threads == 2) any |= free_bits_[1][w];
      if (any == 0) continue;
      // One division per word; the bits of the word walk z (then y, x) from there.
      const OcTreeKey first = box.key(w * 64);
      int x = first[0], y = first[1], z = first[2];
      unsigned at = 0;
      while (any != 0) {
        const unsigned bit = static_cast<unsigned>(__builtin_ctzll(any));
        any &= any - 1;
        for (z += static_cast<int>(bit - at); z >= box.min[2] + box.size[2];) {
          z -= box.size[2];
          if (++y == box.min[1] + box.size[1]) y = box.min[1], ++x;
        }
        at = bit;
        const OcTreeKey key(static_cast<uint16_t>(x), static_cast<uint16_t>(y),
                            static_cast<uint16_t>(z));
        out.push_back(mortonCode(key) << 1 | ((occupied >> bit) & 1));
      }
    }
  };
  if (threads == 2) {
    std::thread helper(extract, words / 2, words, std::ref(scratch_));
    extract(0, words / 2, codes_);
    helper.join();
    codes_.insert(codes_.end(), scratch_.begin(), scratch_.end());
  } else {
    extract(0, words, codes_);
  }
  radixSort(codes_, scratch_, counts_, 49);
  tree.applySortedUpdates(codes_, threads);
}

}  // namespace stereomap::fusion::detail
