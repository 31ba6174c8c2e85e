#include "server/fusion/detail/bulk_insert.hpp"

#include <algorithm>
#include <array>
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

// LSD radix sort of 64-bit values whose set bits are below `bits`.
void radixSort(std::vector<uint64_t>& values, std::vector<uint64_t>& scratch, unsigned bits) {
  constexpr unsigned kDigit = 16;
  scratch.resize(values.size());
  std::vector<uint32_t> counts(size_t{1} << kDigit);
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
// that it visits the same voxels, writing into a bitset instead of a KeyRay.
void castRay(const octomap::OcTree& tree, const point3d& origin, const point3d& end,
             const KeyBox& box, std::vector<uint64_t>& bits) {
  OcTreeKey key_origin, key_end;
  if (!tree.coordToKeyChecked(origin, key_origin) || !tree.coordToKeyChecked(end, key_end)) return;
  if (key_origin == key_end) return;
  setBit(bits, box.index(key_origin));

  point3d direction = end - origin;
  const float length = static_cast<float>(direction.norm());
  direction /= length;
  const double resolution = tree.getResolution();
  int step[3];
  double t_max[3], t_delta[3];
  OcTreeKey current = key_origin;
  for (unsigned i = 0; i < 3; ++i) {
    step[i] = direction(i) > 0.0 ? 1 : direction(i) < 0.0 ? -1 : 0;
    if (step[i] != 0) {
      double border = tree.keyToCoord(current[i]);
      border += static_cast<float>(step[i] * resolution * 0.5);
      t_max[i] = (border - origin(i)) / direction(i);
      t_delta[i] = resolution / std::fabs(direction(i));
    } else {
      t_max[i] = t_delta[i] = std::numeric_limits<double>::max();
    }
  }
  for (;;) {
    unsigned dim;
    if (t_max[0] < t_max[1]) {
      dim = t_max[0] < t_max[2] ? 0 : 2;
    } else {
      dim = t_max[1] < t_max[2] ? 1 : 2;
    }
    current[dim] += step[dim];
    t_max[dim] += t_delta[dim];
    if (current == key_end) return;
    if (std::min(std::min(t_max[0], t_max[1]), t_max[2]) > length) return;
    setBit(bits, box.index(current));
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

void BulkOcTree::applySortedUpdates(const std::vector<uint64_t>& codes) {
  if (codes.empty()) return;
  bool created = false;
  if (root == nullptr) {
    root = new OcTreeNode();  // as updateNode() does for an empty tree
    ++tree_size;
    created = true;
  }
  descend(root, created, 0, codes.data(), codes.data() + codes.size());
}

// Mirrors OccupancyOcTreeBase::updateNodeRecurs for all keys below `node` at once.
void BulkOcTree::descend(OcTreeNode* node, bool node_just_created, unsigned depth,
                         const uint64_t* begin, const uint64_t* end) {
  if (depth == tree_depth) {
    // Each key appears once: one hit or one miss, clamped as updateNode() does.
    updateNodeLogOdds(node, (*begin & 1) ? prob_hit_log : prob_miss_log);
    return;
  }
  // Bits of the child index at this depth: the Morton triplet of bit (15 - depth), which
  // sits above the occupied flag in each code.
  const unsigned shift = 3 * (tree_depth - 1 - depth) + 1;
  for (const uint64_t* group = begin; group != end;) {
    const unsigned child = static_cast<unsigned>((*group >> shift) & 7);
    const uint64_t* group_end =
        std::find_if(group, end, [&](uint64_t c) { return ((c >> shift) & 7) != child; });
    bool created = false;
    if (!nodeChildExists(node, child)) {
      if (!nodeHasChildren(node) && !node_just_created) {
        expandNode(node);  // a pruned node: give it its eight children back
      } else {
        createNodeChild(node, child);
        created = true;
      }
    }
    descend(getNodeChild(node, child), created, depth + 1, group, group_end);
    group = group_end;
  }
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
  codes_.clear();
  for (size_t w = 0; w < words; ++w) {
    const uint64_t occupied = occupied_bits_[w];
    uint64_t free = free_bits_[0][w];
    if (threads == 2) free |= free_bits_[1][w];
    uint64_t any = free | occupied;
    while (any != 0) {
      const unsigned bit = static_cast<unsigned>(__builtin_ctzll(any));
      any &= any - 1;
      const uint64_t is_occupied = (occupied >> bit) & 1;
      codes_.push_back(mortonCode(box.key(w * 64 + bit)) << 1 | is_occupied);
    }
  }
  radixSort(codes_, scratch_, 49);
  tree.applySortedUpdates(codes_);
}

}  // namespace stereomap::fusion::detail
