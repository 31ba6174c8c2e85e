// A session's map as versioned tiles (proto/tiles): what viewers, the tile endpoints and the
// session's counts read, so that none of them ever walks the live octree. The fusion side
// keeps it current from each insertion's changes (work in proportion to the tiles the frame
// changed, never to the map), or rebuilds it from the map after a restore or an import.
//
// Threads: rebuild()/apply() from one writer (the session's fusion worker); everything else
// from any thread. Tiles are immutable once published; a change publishes a new one.
//
//   TileSet tiles("s1", 0.05);
//   tiles.apply(changes);                        // after each insertion
//   auto tile = tiles.find(key);                 // immutable, encoded once per level
//   const std::string& bytes = tile->encoded(0);
#pragma once

#include <array>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "common/geometry.hpp"
#include "proto/tiles/tile_codec.hpp"
#include "server/fusion/occupancy_map.hpp"

namespace stereomap::tiles {

using proto::tiles::kLevels;
using proto::tiles::kTileBits;
using proto::tiles::TileCells;
using proto::tiles::TileKey;

// The tile holding a voxel, and a voxel's code inside its tile.
TileKey tileOf(const fusion::VoxelIndex& voxel);
// Inside a tile: a cell's coordinates from its code, at any level (6 - level bits per axis).
fusion::VoxelIndex cellInTile(uint32_t code);

class Tile {
 public:
  Tile(std::string session, double resolution, TileKey key, uint64_t version,
       std::array<TileCells, kLevels> levels);

  const TileKey& key() const { return key_; }
  uint64_t version() const { return version_; }
  // Occupied cells of a level (0: voxels; level l: cells of 2^l voxels per axis).
  const TileCells& cells(unsigned level) const { return levels_.at(level); }
  // The wire bytes of a level (proto/tiles/FORMAT.md), encoded on first use and kept.
  std::shared_ptr<const std::string> encoded(unsigned level) const;
  // Occupied voxels (level 0) as map indices, in code order.
  std::vector<fusion::VoxelIndex> voxels() const;
  // Smallest and largest voxel index on each axis (level 0 must not be empty).
  std::pair<fusion::VoxelIndex, fusion::VoxelIndex> extent() const;

 private:
  const std::string session_;
  const double resolution_;
  const TileKey key_;
  const uint64_t version_;
  const std::array<TileCells, kLevels> levels_;
  mutable std::mutex encoded_mutex_;
  mutable std::array<std::shared_ptr<const std::string>, kLevels> encoded_;
};

// One tile's entry in the list of a session's tiles.
struct TileInfo {
  TileKey key;
  uint64_t version = 0;
  std::array<uint32_t, kLevels> cells{};  // occupied cells per level
};

struct TileSummary {
  uint64_t version = 0;        // bumps with every change: the newest tile's version
  size_t occupied_voxels = 0;  // at the finest resolution
  common::Box3 bounds;         // of the occupied voxels' cells; empty when none
  size_t tiles = 0;
  int64_t changed_ns = 0;  // wall-clock time of the newest change (0: none yet)
};

class TileSet {
 public:
  TileSet(std::string session, double resolution);

  // Replaces every tile with those of `map` (one walk of the map: restore, import).
  void rebuild(const fusion::OccupancyMap& map);
  // Applies one insertion's changes to the tiles they touch; the changed tiles get new
  // versions. Incomplete changes (or a change of a block larger than a tile) need the map:
  // apply() then returns false and the caller rebuilds.
  bool apply(const fusion::MapChanges& changes);

  TileSummary summary() const;
  std::shared_ptr<const Tile> find(const TileKey& key) const;
  std::vector<TileInfo> list() const;  // in key code order
  // Every tile, in code order (exports: a whole-map read, on request only).
  std::vector<std::shared_ptr<const Tile>> all() const;
  // Keys of the tiles changed (or emptied) after version `since`, each with its newest
  // version; nullopt when `since` is older than the changes kept (the reader resyncs from
  // list()).
  std::optional<std::vector<std::pair<TileKey, uint64_t>>> changedSince(uint64_t since) const;

  const std::string& session() const { return session_; }
  double resolution() const { return resolution_; }
  // Random per TileSet: tells this map's versions from those of an earlier incarnation of
  // the session (versions start again after a restart), e.g. in ETags.
  uint64_t epoch() const { return epoch_; }

 private:
  using TileMap = std::map<uint64_t, std::shared_ptr<const Tile>>;  // by tile code
  // Publishes `tile` (nullptr: the tile at `code` is now empty), under mutex_.
  void publish(uint64_t code, std::shared_ptr<const Tile> tile);
  std::shared_ptr<const Tile> makeTile(uint64_t code, TileCells voxels);

  const std::string session_;
  const double resolution_;
  const uint64_t epoch_;

  mutable std::mutex mutex_;
  TileMap tiles_;
  uint64_t version_ = 0;
  int64_t changed_ns_ = 0;
  size_t occupied_voxels_ = 0;
  // Voxel extents of the tiles, per axis, so that bounds follow removals too.
  std::array<std::multiset<int32_t>, 3> lows_, highs_;
  // Recent changes in version order, for viewers (bounded).
  std::map<uint64_t, uint64_t> recent_;         // version -> tile code
  std::map<uint64_t, uint64_t> latest_change_;  // tile code -> its entry in recent_
  uint64_t forgotten_before_ = 0;               // changes at or below this version were dropped
};

}  // namespace stereomap::tiles
