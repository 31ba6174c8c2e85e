#include "proto/tiles/tile_codec.hpp"

#include <zlib.h>

#include <algorithm>
#include <bit>
#include <charconv>
#include <cstring>

namespace stereomap::proto::tiles {

namespace {

using common::ErrorCode;
using common::makeError;

constexpr char kMagic[4] = {'S', 'M', 'T', 'L'};
constexpr size_t kFixedHeaderBytes = 49;  // up to and including the session id's length
constexpr uint8_t kCompressed = 1;
// Tile indices are voxel keys (16 bits) shifted by kTileBits, centred on zero.
constexpr int32_t kTileKeyLimit = 1 << (16 - kTileBits - 1);

template <typename T>
void put(std::string& out, T value) {
  char bytes[sizeof(T)];
  std::memcpy(bytes, &value, sizeof(T));  // little-endian hosts only (x86-64, arm64)
  out.append(bytes, sizeof(T));
}

template <typename T>
T get(std::string_view bytes, size_t at) {
  T value;
  std::memcpy(&value, bytes.data() + at, sizeof(T));
  return value;
}

// Masks level by level (each level's nodes in code order), then the values.
std::string rawPayload(const TileCells& cells, unsigned mask_levels) {
  std::string raw;
  if (cells.codes.empty()) return raw;
  for (unsigned depth = 0; depth < mask_levels; ++depth) {
    const unsigned shift = 3 * (mask_levels - 1 - depth);
    uint32_t node = cells.codes[0] >> (shift + 3);
    uint8_t mask = 0;
    for (const uint32_t code : cells.codes) {
      if ((code >> (shift + 3)) != node) {
        raw.push_back(static_cast<char>(mask));
        node = code >> (shift + 3);
        mask = 0;
      }
      mask |= static_cast<uint8_t>(1u << ((code >> shift) & 7));
    }
    raw.push_back(static_cast<char>(mask));
  }
  raw.append(reinterpret_cast<const char*>(cells.values.data()), cells.values.size());
  return raw;
}

common::Result<TileCells> cellsFromRaw(std::string_view raw, unsigned mask_levels, uint32_t count) {
  TileCells cells;
  std::vector<uint32_t> nodes = {0}, next;
  size_t at = 0;
  for (unsigned depth = 0; depth < mask_levels && count > 0; ++depth) {
    next.clear();
    for (const uint32_t node : nodes) {
      if (at >= raw.size()) return makeError(ErrorCode::kCorrupt, "tile masks are truncated");
      const auto mask = static_cast<uint8_t>(raw[at++]);
      if (mask == 0) return makeError(ErrorCode::kCorrupt, "tile has an empty child mask");
      for (uint32_t child = 0; child < 8; ++child) {
        if (mask & (1u << child)) next.push_back(node << 3 | child);
      }
      if (next.size() > count) {
        return makeError(ErrorCode::kCorrupt, "tile masks hold more cells than its count");
      }
    }
    nodes.swap(next);
  }
  if (count > 0 && nodes.size() != count) {
    return makeError(ErrorCode::kCorrupt, "tile masks hold " + std::to_string(nodes.size()) +
                                              " cells, its header says " + std::to_string(count));
  }
  if (raw.size() - at != count) {
    return makeError(ErrorCode::kCorrupt, "tile values: " + std::to_string(raw.size() - at) +
                                              " bytes for " + std::to_string(count) + " cells");
  }
  if (count > 0) cells.codes = std::move(nodes);
  cells.values.assign(raw.begin() + static_cast<std::ptrdiff_t>(at), raw.end());
  return cells;
}

}  // namespace

std::string TileKey::text() const {
  return std::to_string(x) + "_" + std::to_string(y) + "_" + std::to_string(z);
}

std::optional<TileKey> TileKey::parse(std::string_view text) {
  int32_t xyz[3];
  const char* at = text.data();
  const char* const end = text.data() + text.size();
  for (int i = 0; i < 3; ++i) {
    if (i > 0) {
      if (at == end || *at != '_') return std::nullopt;
      ++at;
    }
    if (at == end || *at == '+') return std::nullopt;
    const auto [next, error] = std::from_chars(at, end, xyz[i]);
    if (error != std::errc() || next == at) return std::nullopt;
    if (xyz[i] < -kTileKeyLimit || xyz[i] >= kTileKeyLimit) return std::nullopt;
    at = next;
  }
  if (at != end) return std::nullopt;
  return TileKey{xyz[0], xyz[1], xyz[2]};
}

std::string encodeTile(const TileHeader& header, const TileCells& cells) {
  const unsigned mask_levels = kTileBits - header.level;
  const std::string raw = rawPayload(cells, mask_levels);
  std::string stored;
  uint8_t flags = 0;
  if (raw.size() > 32) {  // below that zlib's own header and checksum cost more than it saves
    uLongf size = compressBound(raw.size());
    stored.resize(size);
    if (compress2(reinterpret_cast<Bytef*>(stored.data()), &size,
                  reinterpret_cast<const Bytef*>(raw.data()), raw.size(), 6) == Z_OK &&
        size < raw.size()) {
      stored.resize(size);
      flags |= kCompressed;
    }
  }
  const std::string& payload = (flags & kCompressed) ? stored : raw;
  std::string out;
  out.reserve(kFixedHeaderBytes + header.session.size() + payload.size());
  out.append(kMagic, 4);
  put<uint8_t>(out, kFormatVersion);
  put<uint8_t>(out, header.level);
  put<uint8_t>(out, kTileBits);
  put<uint8_t>(out, flags);
  put<int32_t>(out, header.key.x);
  put<int32_t>(out, header.key.y);
  put<int32_t>(out, header.key.z);
  put<uint64_t>(out, header.version);
  put<uint32_t>(out, static_cast<uint32_t>(cells.size()));
  put<double>(out, header.resolution);
  put<uint32_t>(out, static_cast<uint32_t>(payload.size()));
  put<uint32_t>(out, static_cast<uint32_t>(raw.size()));
  put<uint8_t>(out, static_cast<uint8_t>(header.session.size()));
  out += header.session;
  out += payload;
  return out;
}

common::Result<DecodedTile> decodeTile(std::string_view bytes, size_t* consumed) {
  if (bytes.size() < kFixedHeaderBytes) {
    return makeError(ErrorCode::kCorrupt, "a tile is at least " +
                                              std::to_string(kFixedHeaderBytes) + " bytes, got " +
                                              std::to_string(bytes.size()));
  }
  if (std::memcmp(bytes.data(), kMagic, 4) != 0) {
    return makeError(ErrorCode::kCorrupt, "not a tile (no SMTL magic)");
  }
  if (get<uint8_t>(bytes, 4) != kFormatVersion) {
    return makeError(ErrorCode::kCorrupt,
                     "tile format " + std::to_string(get<uint8_t>(bytes, 4)) + " is not 1");
  }
  DecodedTile tile;
  auto& header = tile.header;
  header.level = get<uint8_t>(bytes, 5);
  if (get<uint8_t>(bytes, 6) != kTileBits || header.level > kTileBits) {
    return makeError(ErrorCode::kCorrupt, "tile size or level out of range");
  }
  const uint8_t flags = get<uint8_t>(bytes, 7);
  if (flags & ~kCompressed) return makeError(ErrorCode::kCorrupt, "unknown tile flags");
  header.key = {get<int32_t>(bytes, 8), get<int32_t>(bytes, 12), get<int32_t>(bytes, 16)};
  header.version = get<uint64_t>(bytes, 20);
  const auto count = get<uint32_t>(bytes, 28);
  header.resolution = get<double>(bytes, 32);
  const auto stored_bytes = get<uint32_t>(bytes, 40);
  const auto raw_bytes = get<uint32_t>(bytes, 44);
  const auto session_bytes = get<uint8_t>(bytes, 48);
  const unsigned mask_levels = kTileBits - header.level;
  const uint64_t max_cells = uint64_t{1} << (3 * mask_levels);
  if (count > max_cells || !(header.resolution > 0) || session_bytes == 0 ||
      session_bytes > kMaxSessionIdBytes) {
    return makeError(ErrorCode::kCorrupt, "tile header out of range");
  }
  // Masks are at most one byte per node above the cells: fewer than count * mask_levels.
  const uint64_t max_raw = uint64_t{count} * (mask_levels + 1);
  if (raw_bytes > max_raw || (!(flags & kCompressed) && stored_bytes != raw_bytes)) {
    return makeError(ErrorCode::kCorrupt, "tile payload sizes out of range");
  }
  const size_t total = kFixedHeaderBytes + session_bytes + stored_bytes;
  if (bytes.size() < total) {
    return makeError(ErrorCode::kCorrupt, "tile is truncated: " + std::to_string(bytes.size()) +
                                              " of " + std::to_string(total) + " bytes");
  }
  header.session.assign(bytes.substr(kFixedHeaderBytes, session_bytes));
  const std::string_view stored = bytes.substr(kFixedHeaderBytes + session_bytes, stored_bytes);
  std::string inflated;
  std::string_view raw = stored;
  if (flags & kCompressed) {
    inflated.resize(raw_bytes);
    uLongf size = raw_bytes;
    if (uncompress(reinterpret_cast<Bytef*>(inflated.data()), &size,
                   reinterpret_cast<const Bytef*>(stored.data()), stored.size()) != Z_OK ||
        size != raw_bytes) {
      return makeError(ErrorCode::kCorrupt, "tile payload does not inflate to its stated size");
    }
    raw = inflated;
  }
  auto cells = cellsFromRaw(raw, mask_levels, count);
  if (!cells) return cells.error();
  tile.cells = std::move(*cells);
  if (consumed != nullptr) *consumed = total;
  return tile;
}

TileCells coarsen(const TileCells& cells) {
  TileCells parent;
  for (size_t i = 0; i < cells.size(); ++i) {
    const uint32_t code = cells.codes[i] >> 3;
    if (!parent.codes.empty() && parent.codes.back() == code) {
      parent.values.back() = std::max(parent.values.back(), cells.values[i]);
    } else {
      parent.codes.push_back(code);
      parent.values.push_back(cells.values[i]);
    }
  }
  return parent;
}

}  // namespace stereomap::proto::tiles
