#include "server/store/catalog.hpp"

#include <gtest/gtest.h>

#include <fstream>

namespace stereomap::store {
namespace {

namespace fs = std::filesystem;

fs::path freshDir(const char* name) {
  std::string leaf = "stereomap-catalog-";
  leaf += std::to_string(::getpid());
  leaf += name;
  fs::path dir = fs::temp_directory_path() / leaf;
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

core::SessionStatus status(const std::string& id, uint64_t frames) {
  core::SessionStatus s;
  s.id = id;
  s.vehicles = {"uav-1", "uav-2"};
  s.frames_fused = frames;
  s.resolution = 0.05;
  s.occupied_voxels = 10 * frames;
  s.bounds.extend({-1, -2, 0});
  s.bounds.extend({3, 4, 2.5});
  return s;
}

TEST(Catalog, RecordsAndUpdatesSessions) {
  const auto dir = freshDir("records");
  {
    auto catalog = Catalog::open(dir);
    ASSERT_TRUE(catalog.ok()) << catalog.error().message;
    EXPECT_TRUE((*catalog)->warning().empty());
    ASSERT_TRUE((*catalog)->record(status("a", 5), 1000).ok());
    ASSERT_TRUE((*catalog)->record(status("b", 7), 2000).ok());
    auto ended = status("a", 9);
    ended.ended = true;
    ASSERT_TRUE((*catalog)->record(ended, 3000).ok());
  }
  auto catalog = Catalog::open(dir);  // survives reopening
  ASSERT_TRUE(catalog.ok());
  auto rows = (*catalog)->list();
  ASSERT_TRUE(rows.ok());
  ASSERT_EQ(rows->size(), 2u);
  const auto& a = rows->at(0).id == "a" ? rows->at(0) : rows->at(1);
  EXPECT_EQ(a.state, "ended");
  EXPECT_EQ(a.frames, 9u);
  EXPECT_EQ(a.vehicles, "uav-1,uav-2");
  EXPECT_DOUBLE_EQ(a.resolution, 0.05);
  EXPECT_EQ(a.journal_bytes, 3000u);
  EXPECT_DOUBLE_EQ(a.bounds.max.z(), 2.5);
  fs::remove_all(dir);
}

TEST(Catalog, DamagedFileIsSetAsideAndRebuilt) {
  const auto dir = freshDir("damaged");
  {
    auto catalog = Catalog::open(dir);
    ASSERT_TRUE(catalog.ok());
    ASSERT_TRUE((*catalog)->record(status("a", 5), 1000).ok());
  }
  fs::remove(dir / "catalog.sqlite-wal");
  fs::remove(dir / "catalog.sqlite-shm");
  {
    std::ofstream garbage(dir / "catalog.sqlite", std::ios::binary | std::ios::trunc);
    garbage << "this is not SQLite any more, just bytes that were once a catalog";
  }
  auto catalog = Catalog::open(dir);
  ASSERT_TRUE(catalog.ok()) << catalog.error().message;
  EXPECT_NE((*catalog)->warning().find("was damaged"), std::string::npos) << (*catalog)->warning();
  EXPECT_NE((*catalog)->warning().find(".corrupt-"), std::string::npos);
  auto rows = (*catalog)->list();
  ASSERT_TRUE(rows.ok());
  EXPECT_TRUE(rows->empty());  // rebuilt: the server refills it from the recovered sessions
  bool kept_aside = false;
  for (const auto& entry : fs::directory_iterator(dir)) {
    kept_aside |= entry.path().filename().string().rfind("catalog.sqlite.corrupt-", 0) == 0;
  }
  EXPECT_TRUE(kept_aside);
  fs::remove_all(dir);
}

}  // namespace
}  // namespace stereomap::store
