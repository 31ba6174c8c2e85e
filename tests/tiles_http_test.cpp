// Map tiles over HTTP (issue 14): a real OctoMap map imported with stereomap-store, served by
// a real server; every level's tiles hold exactly the map's occupied cells; tiles revalidate
// with ETags; bad tile requests get clear errors and leave the server up.
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <filesystem>
#include <fstream>
#include <map>
#include <set>

#include "proto/tiles/tile_codec.hpp"
#include "server/fusion/occupancy_map.hpp"
#include "testing/data.hpp"
#include "tests/support/server_fixture.hpp"

namespace stereomap::testing {
namespace {

using nlohmann::json;
namespace fs = std::filesystem;
constexpr int kDomain = 83;

// Cells of a level from the tiles' bytes, as map cell indices.
std::set<std::tuple<int32_t, int32_t, int32_t>> cellsOf(const std::vector<std::string>& tiles) {
  std::set<std::tuple<int32_t, int32_t, int32_t>> cells;
  for (const auto& bytes : tiles) {
    auto tile = proto::tiles::decodeTile(bytes);
    EXPECT_TRUE(tile) << tile.error().message;
    if (!tile) continue;
    const int32_t edge = 1 << (proto::tiles::kTileBits - tile->header.level);
    for (const uint32_t code : tile->cells.codes) {
      int32_t xyz[3] = {0, 0, 0};
      for (unsigned bit = 0; bit < proto::tiles::kTileBits; ++bit) {
        for (int axis = 0; axis < 3; ++axis) xyz[axis] |= ((code >> (3 * bit + axis)) & 1) << bit;
      }
      const auto& key = tile->header.key;
      cells.insert({key.x * edge + xyz[0], key.y * edge + xyz[1], key.z * edge + xyz[2]});
    }
  }
  return cells;
}

TEST(TilesHttp, AnImportedMapIsServedExactlyAtEveryLevel) {
  const fs::path map_file = kDataDir / "octomap_samples" / "geb079.bt";
  STEREOMAP_SKIP_WITHOUT(map_file);
  const std::string store = makeTempDir("stereomap-tiles");
  const auto imported = runTool({std::string(STEREOMAP_BIN_DIR) + "/stereomap-store", "--store",
                                 store, "import", map_file.string(), "--session", "geb079"});
  ASSERT_EQ(imported.exit_code, 0) << imported.output;
  EXPECT_NE(imported.output.find("185673 occupied voxels"), std::string::npos) << imported.output;

  ServerProcess server(kDomain, {}, store);
  auto listed = json::parse(server.get("/api/sessions").body);
  ASSERT_EQ(listed.size(), 1u);
  EXPECT_EQ(listed[0]["state"], "closed");
  EXPECT_EQ(server.get("/api/sessions/geb079/tiles").status, 409);  // closed: open it first
  ASSERT_EQ(server.request("POST", "/api/sessions/geb079/open").status, 200);

  const auto index = json::parse(server.get("/api/sessions/geb079/tiles").body);
  EXPECT_EQ(index["levels"], 7);
  std::map<int, std::vector<std::string>> bytes_by_level;
  std::map<int, uint64_t> voxels_by_level;
  std::string etag, first_tile;
  for (const auto& entry : index["tiles"]) {
    const int level = entry["level"];
    const std::string path = "/api/sessions/geb079/tiles/" + std::to_string(level) + "/" +
                             entry["key"].get<std::string>();
    const auto reply = server.get(path);
    ASSERT_EQ(reply.status, 200) << path;
    EXPECT_EQ(reply.body.size(), entry["bytes"].get<size_t>());
    EXPECT_EQ(reply.header("Content-Type"), "application/octet-stream");
    bytes_by_level[level].push_back(reply.body);
    voxels_by_level[level] += entry["voxels"].get<uint64_t>();
    if (first_tile.empty()) first_tile = path, etag = reply.header("ETag");
  }
  // OctoMap's own reading of the file, level by level (a cell is occupied when any voxel is).
  std::ifstream in(map_file, std::ios::binary);
  auto map = fusion::OccupancyMap::load(in).value();
  EXPECT_EQ(voxels_by_level[0], 185673u);
  for (int level = 0; level < 7; ++level) {
    const auto expected = map->occupiedCells(16 - level);
    std::set<std::tuple<int32_t, int32_t, int32_t>> truth;
    for (const auto& c : expected) truth.insert({c.x, c.y, c.z});
    EXPECT_EQ(cellsOf(bytes_by_level[level]), truth) << "level " << level;
    EXPECT_EQ(voxels_by_level[level], truth.size()) << "level " << level;
  }
  // Tiles revalidate: the same ETag answers 304 with no body; any other gets the bytes.
  ASSERT_FALSE(etag.empty());
  const auto cached = server.request("GET", first_tile, "", "If-None-Match: " + etag + "\r\n");
  EXPECT_EQ(cached.status, 304);
  EXPECT_TRUE(cached.body.empty());
  EXPECT_EQ(server.request("GET", first_tile, "", "If-None-Match: \"other\"\r\n").status, 200);
  EXPECT_EQ(server.get(first_tile).header("Cache-Control"), "no-cache");
  // The index's versioned URL names this version for good: any cache may keep it; another
  // version is not served under a versioned URL.
  const std::string url = index["tiles"][0]["url"];
  EXPECT_EQ(url, first_tile + "?v=" + etag.substr(1, etag.size() - 2));
  const auto versioned = server.get(url);
  EXPECT_EQ(versioned.status, 200);
  EXPECT_EQ(versioned.body, server.get(first_tile).body);
  EXPECT_EQ(versioned.header("Cache-Control"), "public, max-age=31536000, immutable");
  const auto stale = server.get(first_tile + "?v=0-0");
  EXPECT_EQ(stale.status, 404) << stale.body;
  EXPECT_EQ(stale.header("Cache-Control"), "no-store");
  // HEAD states the length GET would send, with no body.
  const auto head = server.request("HEAD", first_tile);
  EXPECT_EQ(head.status, 200);
  EXPECT_TRUE(head.body.empty());
  EXPECT_EQ(head.header("Content-Length"), std::to_string(server.get(first_tile).body.size()));

  // Bad requests: clear errors, the server stays up.
  for (const char* bad :
       {"/api/sessions/geb079/tiles/7/0_0_0", "/api/sessions/geb079/tiles/x/0_0_0",
        "/api/sessions/geb079/tiles/0/0_0", "/api/sessions/geb079/tiles/0/a_b_c",
        "/api/sessions/geb079/tiles/0/1_2_3_4", "/api/sessions/geb079/tiles/0/99999999999_0_0",
        "/api/sessions/geb079/tiles/00/0_0_0", "/api/sessions/geb079/tiles/-1/0_0_0",
        "/api/sessions/geb079/tiles/0/%2e%2e_0_0"}) {
    const auto reply = server.get(bad);
    EXPECT_EQ(reply.status, 400) << bad << ": " << reply.body;
    EXPECT_NE(reply.body.find("error"), std::string::npos);
  }
  EXPECT_EQ(server.get("/api/sessions/geb079/tiles/0/500_500_500").status, 404);
  EXPECT_EQ(server.get("/api/sessions/geb079/tiles/0").status, 404);
  EXPECT_EQ(server.get("/api/sessions/nothing/tiles").status, 404);
  EXPECT_EQ(server.get("/healthz").status, 200);
  std::error_code ec;
  fs::remove_all(store, ec);
}

TEST(TilesHttp, ImportRefusesDamagedFilesAndWritesNothing) {
  const fs::path map_file = kDataDir / "octomap_samples" / "geb079.bt";
  STEREOMAP_SKIP_WITHOUT(map_file);
  const std::string store = makeTempDir("stereomap-import");
  std::ifstream in(map_file, std::ios::binary);
  const std::string good((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const std::string bad = store + "-bad.bt";
  for (const size_t size : {size_t{0}, size_t{40}, good.size() / 2, good.size() - 1}) {
    std::ofstream(bad, std::ios::binary) << good.substr(0, size);
    const auto run = runTool({std::string(STEREOMAP_BIN_DIR) + "/stereomap-store", "--store", store,
                              "import", bad, "--session", "bad"});
    EXPECT_EQ(run.exit_code, 1) << run.output;
    EXPECT_NE(run.output.find("error: " + bad), std::string::npos) << run.output;
    EXPECT_FALSE(fs::exists(fs::path(store) / "bad"));
  }
  const auto bad_id = runTool({std::string(STEREOMAP_BIN_DIR) + "/stereomap-store", "--store",
                               store, "import", map_file.string(), "--session", "../x"});
  EXPECT_EQ(bad_id.exit_code, 1) << bad_id.output;
  std::error_code ec;
  fs::remove(bad, ec);
  fs::remove_all(store, ec);
}

}  // namespace
}  // namespace stereomap::testing
