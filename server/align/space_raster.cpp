#include "server/align/space_raster.hpp"

#include <algorithm>
#include <cassert>
#include <cmath>

namespace stereomap::align {

namespace {

int64_t cellOf(double coordinate, double edge) {
  return static_cast<int64_t>(std::floor(coordinate / edge));
}

uint64_t hashKey(int64_t x, int64_t y, int64_t z) {
  // Cell indices fit 16 bits plus sign at any depth: 21 bits an axis is plenty.
  constexpr int64_t kBias = int64_t{1} << 20;
  return static_cast<uint64_t>(x + kBias) | static_cast<uint64_t>(y + kBias) << 21 |
         static_cast<uint64_t>(z + kBias) << 42;
}

}  // namespace

CellRaster::CellRaster(const std::vector<uint64_t>& codes, unsigned depth, double edge)
    : edge_(edge) {
  const int64_t offset = fusion::kKeyOffset >> (fusion::kTreeDepth - depth);
  std::vector<int64_t> cells;
  cells.reserve(codes.size() * 3);
  int64_t lo[3] = {INT64_MAX, INT64_MAX, INT64_MAX}, hi[3] = {INT64_MIN, INT64_MIN, INT64_MIN};
  for (const uint64_t code : codes) {
    for (unsigned axis = 0; axis < 3; ++axis) {
      const int64_t index =
          static_cast<int64_t>(fusion::detail::compactBits(code >> axis)) - offset;
      cells.push_back(index);
      lo[axis] = std::min(lo[axis], index);
      hi[axis] = std::max(hi[axis], index);
    }
  }
  if (codes.empty()) return;
  size_t volume = 1;
  for (unsigned axis = 0; axis < 3; ++axis) {
    // One cell of margin: a lookup's neighbours never leave the raster.
    low_[axis] = lo[axis] - 1;
    size_[axis] = hi[axis] - lo[axis] + 3;
    volume *= static_cast<size_t>(size_[axis]);
  }
  if (volume <= kMaxDenseCells) {
    dense_.assign(volume, 0);
    for (size_t i = 0; i < cells.size(); i += 3) {
      dense_[static_cast<size_t>(((cells[i + 2] - low_[2]) * size_[1] + cells[i + 1] - low_[1]) *
                                     size_[0] +
                                 cells[i] - low_[0])] = 1;
    }
  } else {
    hashed_.reserve(codes.size());
    for (size_t i = 0; i < cells.size(); i += 3) {
      hashed_.insert(hashKey(cells[i], cells[i + 1], cells[i + 2]));
    }
  }
}

bool CellRaster::occupied(int64_t x, int64_t y, int64_t z) const {
  if (!dense_.empty()) {
    x -= low_[0], y -= low_[1], z -= low_[2];
    if (x < 0 || y < 0 || z < 0 || x >= size_[0] || y >= size_[1] || z >= size_[2]) return false;
    return dense_[static_cast<size_t>((z * size_[1] + y) * size_[0] + x)] != 0;
  }
  return hashed_.count(hashKey(x, y, z)) > 0;
}

// Centres within 1.5 edges of p lie in p's cell or its 26 neighbours. kFirst: stop at the
// first one within reach (its distance, not the nearest).
template <bool kFirst>
double CellRaster::search(const common::Vec3& p, double reach) const {
  assert(reach <= 1.5 * edge_);
  const int64_t cx = cellOf(p.x(), edge_), cy = cellOf(p.y(), edge_), cz = cellOf(p.z(), edge_);
  const double reach2 = reach * reach;
  double best = -1;
  const auto consider = [&](int64_t x, int64_t y, int64_t z) {
    if (!occupied(x, y, z)) return false;
    const common::Vec3 centre((static_cast<double>(x) + 0.5) * edge_,
                              (static_cast<double>(y) + 0.5) * edge_,
                              (static_cast<double>(z) + 0.5) * edge_);
    const double d2 = (centre - p).squaredNorm();
    if (d2 > reach2 || (best >= 0 && d2 >= best)) return false;
    best = d2;
    return kFirst;
  };
  // p's own cell first: its centre is always within reach when the reach is 1.5 edges.
  if (consider(cx, cy, cz)) return best;
  for (int64_t z = cz - 1; z <= cz + 1; ++z) {
    for (int64_t y = cy - 1; y <= cy + 1; ++y) {
      for (int64_t x = cx - 1; x <= cx + 1; ++x) {
        if ((x != cx || y != cy || z != cz) && consider(x, y, z)) return best;
      }
    }
  }
  return best;
}

double CellRaster::nearest2(const common::Vec3& p, double reach) const {
  return search<false>(p, reach);
}

bool CellRaster::near(const common::Vec3& p, double reach) const {
  return search<true>(p, reach) >= 0;
}

ClassRaster::ClassRaster(const fusion::OccupancyMap& map, double margin_m)
    : map_(map), resolution_(map.resolution()) {
  common::Box3 box = map.occupiedBounds();
  if (box.empty()) return;
  box.min.array() -= margin_m;
  box.max.array() += margin_m;
  size_t volume = 1;
  for (unsigned axis = 0; axis < 3; ++axis) {
    low_[axis] = cellOf(box.min[axis], resolution_);
    size_[axis] = cellOf(box.max[axis], resolution_) - low_[axis] + 1;
    volume *= static_cast<size_t>(size_[axis]);
  }
  if (volume > kMaxCells) return;
  classes_.assign((volume + 3) / 4, 0);
  // Known nodes only (unknown stays 0); a pruned block fills all of its voxels in the box.
  map.visitKnown(box, [&](const common::Vec3& corner, double edge, fusion::Occupancy occupancy) {
    if (occupancy == fusion::Occupancy::kUnknown) return;
    const auto bits = static_cast<uint8_t>(occupancy);
    const auto voxels = static_cast<int64_t>(std::llround(edge / resolution_));
    int64_t from[3], to[3];
    for (unsigned axis = 0; axis < 3; ++axis) {
      const auto first = static_cast<int64_t>(std::llround(corner[axis] / resolution_));
      from[axis] = std::max(first, low_[axis]) - low_[axis];
      to[axis] = std::min(first + voxels, low_[axis] + size_[axis]) - low_[axis];
    }
    for (int64_t z = from[2]; z < to[2]; ++z) {
      for (int64_t y = from[1]; y < to[1]; ++y) {
        for (int64_t x = from[0]; x < to[0]; ++x) {
          const auto i = static_cast<size_t>((z * size_[1] + y) * size_[0] + x);
          classes_[i / 4] |= static_cast<uint8_t>(bits << (2 * (i % 4)));
        }
      }
    }
  });
}

fusion::Occupancy ClassRaster::at(const common::Vec3& p) const {
  if (classes_.empty()) return map_.query(p);
  const int64_t x = cellOf(p.x(), resolution_) - low_[0];
  const int64_t y = cellOf(p.y(), resolution_) - low_[1];
  const int64_t z = cellOf(p.z(), resolution_) - low_[2];
  if (x < 0 || y < 0 || z < 0 || x >= size_[0] || y >= size_[1] || z >= size_[2]) {
    return map_.query(p);
  }
  const auto i = static_cast<size_t>((z * size_[1] + y) * size_[0] + x);
  return static_cast<fusion::Occupancy>((classes_[i / 4] >> (2 * (i % 4))) & 3);
}

}  // namespace stereomap::align
