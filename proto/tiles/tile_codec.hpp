// The tile wire format (normative spec: proto/tiles/FORMAT.md): one level of detail of one
// tile of a session's map as bytes for viewers and HTTP caches, and back. A tile is a cube of
// 64 finest voxels per axis; level l holds its occupied cells of 2^l voxels per axis (level 0
// the voxels themselves), each with its occupancy probability quantised to a byte.
//
//   const std::string bytes = encodeTile(header, cells);
//   auto tile = decodeTile(bytes);  // an Error for anything malformed, never a crash
#pragma once

#include <compare>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "common/result.hpp"

namespace stereomap::proto::tiles {

constexpr unsigned kTileBits = 6;            // a tile is 2^6 = 64 finest voxels per axis
constexpr unsigned kLevels = kTileBits + 1;  // level 0 (voxels) .. 6 (one cell per tile)
constexpr uint8_t kFormatVersion = 1;
constexpr size_t kMaxSessionIdBytes = 64;

// A tile's place: tile (x, y, z) holds voxels with index / 64 (rounded down) = (x, y, z).
struct TileKey {
  int32_t x = 0, y = 0, z = 0;
  auto operator<=>(const TileKey&) const = default;
  std::string text() const;  // "x_y_z", as in URLs
  // Parses "x_y_z" (decimal integers, '-' allowed, nothing else); nullopt when malformed or
  // outside the map's key range.
  static std::optional<TileKey> parse(std::string_view text);
};

// The occupied cells of one level of one tile: cell codes are the Morton codes of the cells'
// coordinates inside the tile (x lowest, 6 - level bits per axis), ascending, one value each.
struct TileCells {
  std::vector<uint32_t> codes;
  std::vector<uint8_t> values;  // round(255 P): the cell's occupancy probability
  size_t size() const { return codes.size(); }
  bool operator==(const TileCells&) const = default;
};

struct TileHeader {
  std::string session;
  TileKey key;
  uint8_t level = 0;
  uint64_t version = 0;
  double resolution = 0;  // metres, the finest voxel's edge
};

struct DecodedTile {
  TileHeader header;
  TileCells cells;
};

// The tile's bytes: header, then child masks and values (compressed when that is smaller).
// `cells` must be valid for `header.level` (ascending codes below 8^(6 - level)).
std::string encodeTile(const TileHeader& header, const TileCells& cells);

// One tile from the front of `bytes`; `consumed` (optional) gets its length, so that tiles
// sent back to back can be read one after another.
common::Result<DecodedTile> decodeTile(std::string_view bytes, size_t* consumed = nullptr);

// Cells of level `level` + 1 from those of `level`: a cell is occupied when any of its eight
// children is, with the largest of their values (OctoMap keeps inner nodes at the max).
TileCells coarsen(const TileCells& cells);

}  // namespace stereomap::proto::tiles
