#include "server/tiles/tile_set.hpp"

#include <algorithm>
#include <random>

#include "common/time.hpp"

namespace stereomap::tiles {

namespace {

using proto::tiles::kTileBits;
using proto::tiles::TileHeader;

constexpr unsigned kTileCodeShift = 3 * kTileBits;           // voxel code -> tile code
constexpr uint32_t kLocalMask = (1u << kTileCodeShift) - 1;  // voxel code -> code in tile
constexpr unsigned kTileDepth = fusion::kTreeDepth - kTileBits;
constexpr size_t kRecentChangesKept = 1 << 16;

TileKey keyOfTileCode(uint64_t tile_code) {
  const fusion::VoxelIndex first = fusion::voxelOfCode(tile_code << kTileCodeShift);
  return tileOf(first);
}

uint64_t tileCodeOf(const TileKey& key) {
  const fusion::VoxelIndex first{key.x << kTileBits, key.y << kTileBits, key.z << kTileBits};
  return fusion::voxelCode(first) >> kTileCodeShift;
}

}  // namespace

fusion::VoxelIndex cellInTile(uint32_t code) {
  const fusion::VoxelIndex v = fusion::voxelOfCode(code);
  return {v.x + fusion::kKeyOffset, v.y + fusion::kKeyOffset, v.z + fusion::kKeyOffset};
}

TileKey tileOf(const fusion::VoxelIndex& voxel) {
  return {voxel.x >> kTileBits, voxel.y >> kTileBits, voxel.z >> kTileBits};
}

Tile::Tile(std::string session, double resolution, TileKey key, uint64_t version,
           std::array<TileCells, kLevels> levels)
    : session_(std::move(session)),
      resolution_(resolution),
      key_(key),
      version_(version),
      levels_(std::move(levels)) {}

std::shared_ptr<const std::string> Tile::encoded(unsigned level) const {
  std::lock_guard lock(encoded_mutex_);
  auto& bytes = encoded_.at(level);
  if (!bytes) {
    const TileHeader header{session_, key_, static_cast<uint8_t>(level), version_, resolution_};
    bytes = std::make_shared<const std::string>(proto::tiles::encodeTile(header, levels_[level]));
  }
  return bytes;
}

std::vector<fusion::VoxelIndex> Tile::voxels() const {
  std::vector<fusion::VoxelIndex> voxels;
  voxels.reserve(levels_[0].size());
  const fusion::VoxelIndex base{key_.x << kTileBits, key_.y << kTileBits, key_.z << kTileBits};
  for (const uint32_t code : levels_[0].codes) {
    const auto local = cellInTile(code);
    voxels.push_back({base.x + local.x, base.y + local.y, base.z + local.z});
  }
  return voxels;
}

std::pair<fusion::VoxelIndex, fusion::VoxelIndex> Tile::extent() const {
  fusion::VoxelIndex low{1 << kTileBits, 1 << kTileBits, 1 << kTileBits}, high{-1, -1, -1};
  for (const uint32_t code : levels_[0].codes) {
    const auto v = cellInTile(code);
    low = {std::min(low.x, v.x), std::min(low.y, v.y), std::min(low.z, v.z)};
    high = {std::max(high.x, v.x), std::max(high.y, v.y), std::max(high.z, v.z)};
  }
  const fusion::VoxelIndex base{key_.x << kTileBits, key_.y << kTileBits, key_.z << kTileBits};
  return {{base.x + low.x, base.y + low.y, base.z + low.z},
          {base.x + high.x, base.y + high.y, base.z + high.z}};
}

TileSet::TileSet(std::string session, double resolution)
    : session_(std::move(session)),
      resolution_(resolution),
      epoch_((uint64_t{std::random_device{}()} << 32) ^ std::random_device{}()) {}

std::shared_ptr<const Tile> TileSet::makeTile(uint64_t code, TileCells voxels) {
  std::array<TileCells, kLevels> levels;
  levels[0] = std::move(voxels);
  for (unsigned level = 1; level < kLevels; ++level) {
    levels[level] = proto::tiles::coarsen(levels[level - 1]);
  }
  return std::make_shared<const Tile>(session_, resolution_, keyOfTileCode(code), version_ + 1,
                                      std::move(levels));
}

void TileSet::publish(uint64_t code, std::shared_ptr<const Tile> tile) {
  const auto found = tiles_.find(code);
  const std::shared_ptr<const Tile> old = found == tiles_.end() ? nullptr : found->second;
  // Extents before taking the lock: they decode every voxel, and readers should not wait.
  std::optional<std::pair<fusion::VoxelIndex, fusion::VoxelIndex>> old_extent, new_extent;
  if (old) old_extent = old->extent();
  if (tile) new_extent = tile->extent();

  std::lock_guard lock(mutex_);
  ++version_;
  changed_ns_ = common::nowNs();
  if (old) {
    occupied_voxels_ -= old->cells(0).size();
    const auto& [low, high] = *old_extent;
    lows_[0].erase(lows_[0].find(low.x)), lows_[1].erase(lows_[1].find(low.y));
    lows_[2].erase(lows_[2].find(low.z));
    highs_[0].erase(highs_[0].find(high.x)), highs_[1].erase(highs_[1].find(high.y));
    highs_[2].erase(highs_[2].find(high.z));
  }
  if (tile) {
    occupied_voxels_ += tile->cells(0).size();
    const auto& [low, high] = *new_extent;
    lows_[0].insert(low.x), lows_[1].insert(low.y), lows_[2].insert(low.z);
    highs_[0].insert(high.x), highs_[1].insert(high.y), highs_[2].insert(high.z);
    tiles_[code] = std::move(tile);
  } else if (old) {
    tiles_.erase(code);
  }
  // One entry per tile: its newest change.
  if (const auto last = latest_change_.find(code); last != latest_change_.end()) {
    recent_.erase(last->second);
  }
  recent_[version_] = code;
  latest_change_[code] = version_;
  while (recent_.size() > kRecentChangesKept) {
    forgotten_before_ = recent_.begin()->first;
    latest_change_.erase(recent_.begin()->second);
    recent_.erase(recent_.begin());
  }
}

void TileSet::rebuild(const fusion::OccupancyMap& map) {
  std::map<uint64_t, TileCells> voxels_by_tile;
  TileCells* current = nullptr;
  uint64_t current_code = ~uint64_t{0};
  map.visitOccupied(0, 0, [&](uint64_t code, unsigned depth, uint8_t value) {
    // A pruned block: all its voxels (consecutive codes), in as many tiles as it spans.
    const uint64_t count = uint64_t{1} << (3 * (fusion::kTreeDepth - depth));
    for (uint64_t c = code; c < code + count; ++c) {
      const uint64_t tile_code = c >> kTileCodeShift;
      if (tile_code != current_code) {
        current = &voxels_by_tile[tile_code];
        current_code = tile_code;
      }
      current->codes.push_back(static_cast<uint32_t>(c & kLocalMask));
      current->values.push_back(value);
    }
  });
  for (auto& [code, voxels] : voxels_by_tile) publish(code, makeTile(code, std::move(voxels)));
  // Tiles that are gone.
  std::vector<uint64_t> stale;
  for (const auto& [code, tile] : tiles_) {
    if (!voxels_by_tile.contains(code)) stale.push_back(code);
  }
  for (const uint64_t code : stale) publish(code, nullptr);
}

bool TileSet::apply(const fusion::MapChanges& changes) {
  if (!changes.complete) return false;
  for (const auto& change : changes.voxels) {
    if (change.depth < kTileDepth) return false;  // a block larger than a tile
  }
  const auto& all = changes.voxels;
  for (size_t begin = 0; begin < all.size();) {
    const uint64_t code = all[begin].code >> kTileCodeShift;
    size_t end = begin;
    while (end < all.size() && (all[end].code >> kTileCodeShift) == code) ++end;
    // Merge the tile's voxels with its changes (both in code order; changes never overlap).
    const auto found = tiles_.find(code);
    static const TileCells kNone;
    const TileCells& old = found == tiles_.end() ? kNone : found->second->cells(0);
    TileCells voxels;
    voxels.codes.reserve(old.size() + 64);
    voxels.values.reserve(old.size() + 64);
    size_t i = 0;
    for (size_t c = begin; c < end; ++c) {
      const auto& change = all[c];
      const auto first = static_cast<uint32_t>(change.code & kLocalMask);
      const uint32_t count = 1u << (3 * (fusion::kTreeDepth - change.depth));
      for (; i < old.size() && old.codes[i] < first; ++i) {
        voxels.codes.push_back(old.codes[i]);
        voxels.values.push_back(old.values[i]);
      }
      while (i < old.size() && old.codes[i] < first + count) ++i;
      if (change.occupied) {
        for (uint32_t v = first; v < first + count; ++v) {
          voxels.codes.push_back(v);
          voxels.values.push_back(change.value);
        }
      }
    }
    voxels.codes.insert(voxels.codes.end(), old.codes.begin() + static_cast<std::ptrdiff_t>(i),
                        old.codes.end());
    voxels.values.insert(voxels.values.end(), old.values.begin() + static_cast<std::ptrdiff_t>(i),
                         old.values.end());
    if (voxels.codes.empty()) {
      if (found != tiles_.end()) publish(code, nullptr);
    } else if (voxels != old) {
      publish(code, makeTile(code, std::move(voxels)));
    }
    begin = end;
  }
  return true;
}

TileSummary TileSet::summary() const {
  std::lock_guard lock(mutex_);
  TileSummary summary;
  summary.version = version_;
  summary.changed_ns = changed_ns_;
  summary.occupied_voxels = occupied_voxels_;
  summary.tiles = tiles_.size();
  if (!tiles_.empty()) {
    const common::Vec3 low(*lows_[0].begin(), *lows_[1].begin(), *lows_[2].begin());
    const common::Vec3 high(*highs_[0].rbegin(), *highs_[1].rbegin(), *highs_[2].rbegin());
    summary.bounds.extend(low * resolution_);
    summary.bounds.extend((high + common::Vec3::Ones()) * resolution_);
  }
  return summary;
}

std::shared_ptr<const Tile> TileSet::find(const TileKey& key) const {
  std::lock_guard lock(mutex_);
  const auto found = tiles_.find(tileCodeOf(key));
  return found == tiles_.end() ? nullptr : found->second;
}

std::vector<TileInfo> TileSet::list() const {
  std::lock_guard lock(mutex_);
  std::vector<TileInfo> list;
  list.reserve(tiles_.size());
  for (const auto& [code, tile] : tiles_) {
    TileInfo info{tile->key(), tile->version(), {}};
    for (unsigned level = 0; level < kLevels; ++level) {
      info.cells[level] = static_cast<uint32_t>(tile->cells(level).size());
    }
    list.push_back(info);
  }
  return list;
}

std::vector<std::shared_ptr<const Tile>> TileSet::all() const {
  std::lock_guard lock(mutex_);
  std::vector<std::shared_ptr<const Tile>> all;
  all.reserve(tiles_.size());
  for (const auto& [code, tile] : tiles_) all.push_back(tile);
  return all;
}

std::optional<std::vector<std::pair<TileKey, uint64_t>>> TileSet::changedSince(
    uint64_t since) const {
  std::lock_guard lock(mutex_);
  if (since < forgotten_before_) return std::nullopt;
  std::vector<std::pair<TileKey, uint64_t>> changed;
  for (auto it = recent_.upper_bound(since); it != recent_.end(); ++it) {
    changed.emplace_back(keyOfTileCode(it->second), it->first);
  }
  return changed;
}

}  // namespace stereomap::tiles
