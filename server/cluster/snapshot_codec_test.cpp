#include "server/cluster/snapshot_codec.hpp"

#include <gtest/gtest.h>

namespace stereomap::cluster {
namespace {

TEST(SnapshotCodec, PackedSnapshotsComeBackWholeAndSmaller) {
  std::string ot = "# Octomap OcTree file\nid OcTree\nsize 3\nres 0.1\ndata\n";
  for (int i = 0; i < 100000; ++i) ot += static_cast<char>(i % 7 == 0 ? i & 0xff : 0);
  const std::string packed = packSnapshot(ot);
  EXPECT_LT(packed.size(), ot.size() / 4);
  auto unpacked = unpackSnapshot(packed);
  ASSERT_TRUE(unpacked) << unpacked.error().message;
  EXPECT_EQ(*unpacked, ot);
}

TEST(SnapshotCodec, ARawOtIsReadAsItIsAndADamagedFrameIsRefused) {
  auto raw = unpackSnapshot("# Octomap OcTree file\n");
  ASSERT_TRUE(raw);
  EXPECT_EQ(*raw, "# Octomap OcTree file\n");
  std::string packed = packSnapshot(std::string(50000, 'x'));
  packed.resize(packed.size() / 2);
  EXPECT_FALSE(unpackSnapshot(packed));
  std::string lying = packSnapshot(std::string(50000, 'x'));
  lying[lying.size() - 3] ^= 0x55;
  auto damaged = unpackSnapshot(lying);
  if (damaged) {
    EXPECT_NE(*damaged, std::string(50000, 'x'));  // never silently wrong
  }
}

}  // namespace
}  // namespace stereomap::cluster
