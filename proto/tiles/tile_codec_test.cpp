#include "proto/tiles/tile_codec.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <random>
#include <sstream>

namespace stereomap::proto::tiles {
namespace {

// Morton code of a voxel's coordinates inside its tile (x lowest).
uint32_t localCode(uint32_t x, uint32_t y, uint32_t z) {
  uint32_t code = 0;
  for (unsigned bit = 0; bit < kTileBits; ++bit) {
    code |= ((x >> bit) & 1) << (3 * bit) | ((y >> bit) & 1) << (3 * bit + 1) |
            ((z >> bit) & 1) << (3 * bit + 2);
  }
  return code;
}

// A sloped 40 x 30 surface with a post, values varying: the golden tile's level 0.
TileCells goldenVoxels() {
  TileCells cells;
  std::vector<std::pair<uint32_t, uint8_t>> voxels;
  for (uint32_t x = 3; x < 43; ++x) {
    for (uint32_t y = 10; y < 40; ++y) {
      voxels.emplace_back(localCode(x, y, 5 + x / 8),
                          static_cast<uint8_t>(128 + (x * 7 + y) % 120));
    }
  }
  for (uint32_t z = 0; z < 64; ++z) voxels.emplace_back(localCode(60, 2, z), 250);
  std::sort(voxels.begin(), voxels.end());
  for (const auto& [code, value] : voxels) {
    cells.codes.push_back(code);
    cells.values.push_back(value);
  }
  return cells;
}

TileCells atLevel(TileCells cells, unsigned level) {
  for (unsigned l = 0; l < level; ++l) cells = coarsen(cells);
  return cells;
}

struct Golden {
  const char* file;
  TileHeader header;
  TileCells cells;
};

std::vector<Golden> goldens() {
  std::vector<Golden> all;
  // (g++ 12 warns falsely about strings in a braced list of these; built one by one.)
  auto add = [&](const char* file, uint8_t level, uint64_t version, TileCells cells) {
    Golden golden;
    golden.file = file;
    golden.header.session = "golden-1";
    golden.header.key = {-3, 7, 0};
    golden.header.level = level;
    golden.header.version = version;
    golden.header.resolution = 0.05;
    golden.cells = std::move(cells);
    all.push_back(std::move(golden));
  };
  add("surface_level0.tile", 0, 41, goldenVoxels());
  add("surface_level3.tile", 3, 41, atLevel(goldenVoxels(), 3));
  add("surface_level6.tile", 6, 41, atLevel(goldenVoxels(), 6));
  add("empty_level0.tile", 0, 42, {});
  return all;
}

std::string fixturePath(const std::string& name) {
  return std::string(STEREOMAP_TILE_FIXTURES) + "/" + name;
}

std::string readFile(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::ostringstream bytes;
  bytes << in.rdbuf();
  return bytes.str();
}

// The JavaScript viewer's tests decode the same files and compare with cells.json.
TEST(TileCodec, GoldenBytesAreStable) {
  const bool write = std::getenv("STEREOMAP_WRITE_FIXTURES") != nullptr;
  std::ostringstream json;
  json << "[\n";
  const auto all = goldens();
  for (size_t g = 0; g < all.size(); ++g) {
    const auto& golden = all[g];
    const std::string bytes = encodeTile(golden.header, golden.cells);
    if (write) std::ofstream(fixturePath(golden.file), std::ios::binary) << bytes;
    EXPECT_EQ(bytes, readFile(fixturePath(golden.file)))
        << golden.file << " changed: the format is normative (FORMAT.md); "
        << "STEREOMAP_WRITE_FIXTURES=1 rewrites the fixtures after a deliberate change";
    json << "  {\"file\": \"" << golden.file << "\", \"session\": \"" << golden.header.session
         << "\", \"key\": [" << golden.header.key.x << ", " << golden.header.key.y << ", "
         << golden.header.key.z << "], \"level\": " << int(golden.header.level)
         << ", \"version\": " << golden.header.version
         << ", \"resolution\": " << golden.header.resolution << ",\n   \"codes\": [";
    for (size_t i = 0; i < golden.cells.size(); ++i) {
      json << (i ? ", " : "") << golden.cells.codes[i];
    }
    json << "],\n   \"values\": [";
    for (size_t i = 0; i < golden.cells.size(); ++i) {
      json << (i ? ", " : "") << int(golden.cells.values[i]);
    }
    json << "]}" << (g + 1 < all.size() ? "," : "") << "\n";
  }
  json << "]\n";
  if (write) std::ofstream(fixturePath("cells.json")) << json.str();
  EXPECT_EQ(json.str(), readFile(fixturePath("cells.json")));
}

TEST(TileCodec, DecodesWhatItEncodesAtEveryLevel) {
  TileCells voxels = goldenVoxels();
  for (uint8_t level = 0; level < kLevels; ++level) {
    const TileHeader header{"s", {1, -2, 3}, level, 9, 0.2};
    const std::string bytes = encodeTile(header, voxels);
    size_t consumed = 0;
    auto tile = decodeTile(bytes + "trailing", &consumed);
    ASSERT_TRUE(tile) << tile.error().message;
    EXPECT_EQ(consumed, bytes.size());
    EXPECT_EQ(tile->cells, voxels) << "level " << int(level);
    EXPECT_EQ(tile->header.key, header.key);
    EXPECT_EQ(tile->header.version, 9u);
    EXPECT_EQ(tile->header.level, level);
    EXPECT_EQ(tile->header.session, "s");
    voxels = coarsen(voxels);
  }
}

TEST(TileCodec, CoarserLevelsKeepAnyOccupiedChildWithTheLargestValue) {
  TileCells voxels;
  voxels.codes = {0, 1, 7, 8, 64};
  voxels.values = {130, 200, 140, 150, 160};
  const TileCells parent = coarsen(voxels);
  EXPECT_EQ(parent.codes, (std::vector<uint32_t>{0, 1, 8}));
  EXPECT_EQ(parent.values, (std::vector<uint8_t>{200, 150, 160}));
}

TEST(TileCodec, SurfacesCostWellUnderOneBytePerVoxel) {
  const TileCells voxels = goldenVoxels();
  const std::string bytes = encodeTile({"s", {}, 0, 1, 0.05}, voxels);
  EXPECT_LT(static_cast<double>(bytes.size()) / voxels.size(), 1.0);
}

TEST(TileCodec, RejectsEveryDamagedOrTruncatedTile) {
  const std::string good =
      encodeTile({"session", {4, 5, 6}, 1, 3, 0.1}, atLevel(goldenVoxels(), 1));
  for (size_t size = 0; size < good.size(); ++size) {
    EXPECT_FALSE(decodeTile(good.substr(0, size))) << "truncated to " << size;
  }
  // Every single flipped byte is either rejected or decodes into a well-formed tile.
  std::mt19937 rng(3);
  for (size_t at = 0; at < good.size(); ++at) {
    std::string bad = good;
    bad[at] = static_cast<char>(bad[at] ^ (1 + rng() % 255));
    auto tile = decodeTile(bad);
    if (!tile) continue;
    const auto& cells = tile->cells;
    ASSERT_EQ(cells.codes.size(), cells.values.size());
    ASSERT_TRUE(std::is_sorted(cells.codes.begin(), cells.codes.end()));
    ASSERT_TRUE(cells.codes.empty() ||
                cells.codes.back() < (1u << 3 * (kTileBits - tile->header.level)));
  }
  // A header that claims a huge payload allocates nothing before the size checks.
  std::string huge = good;
  const uint32_t claim = 0x7fffffff;
  std::memcpy(huge.data() + 44, &claim, 4);
  EXPECT_FALSE(decodeTile(huge));
}

TEST(TileKey, ParsesOnlyCanonicalText) {
  EXPECT_EQ(TileKey::parse("1_-2_30"), (TileKey{1, -2, 30}));
  EXPECT_EQ((TileKey{-512, 0, 511}).text(), "-512_0_511");
  for (const char* bad : {"", "1_2", "1_2_3_4", "1__2_3", "a_2_3", "1_2_3 ", "+1_2_3", "1_2_512",
                          "1_-513_0", "99999999999_1_1", "1_2_3/..", "0x1_2_3"}) {
    EXPECT_FALSE(TileKey::parse(bad)) << bad;
  }
}

}  // namespace
}  // namespace stereomap::proto::tiles
