#include "onboard/link/cloud_link.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <set>
#include <stdexcept>

#include "onboard/stereo/depth.hpp"

namespace stereomap::link {
namespace {

using common::PointCloud;
using common::Rigid3;
using common::Vec3;
using common::Vec3f;

constexpr int64_t kFrameNs = 100'000'000;  // 10 Hz

// A wall 2-4 m ahead of the camera (z), a point every 2 cm: many points per 0.1 m voxel.
PointCloud wall(double offset_x = 0) {
  PointCloud cloud;
  for (double x = -1; x <= 1; x += 0.02) {
    for (double y = -0.5; y <= 0.5; y += 0.02) {
      cloud.points.emplace_back(static_cast<float>(x + offset_x), static_cast<float>(y),
                                static_cast<float>(3 + 0.5 * x));
      cloud.intensity.push_back(static_cast<uint8_t>(100 + 50 * x));
    }
  }
  return cloud;
}

// A camera pose off the map's axes, so the map's voxels are not the camera's.
Rigid3 pose(double x = 0) {
  return {common::Quat(Eigen::AngleAxisd(0.3, Vec3::UnitY())) *
              common::Quat(Eigen::AngleAxisd(-0.2, Vec3::UnitX())),
          Vec3(1.234 + x, -0.567, 0.89)};
}

std::set<uint64_t> mapVoxels(const PointCloud& cloud, const Rigid3& T_map_camera) {
  std::set<uint64_t> keys;
  for (const auto& p : cloud.points)
    keys.insert(stereo::gridKey(T_map_camera * p.cast<double>(), 0.1));
  return keys;
}

TEST(CloudLink, ThinsToOnePointPerMapVoxelWithEveryRayEndingInItsVoxel) {
  CloudLink link({.map_resolution_m = 0.1});
  const PointCloud cloud = wall();
  const auto thinned = link.prepare(cloud, pose(), 0);
  ASSERT_TRUE(thinned);
  const auto voxels = mapVoxels(cloud, pose());
  EXPECT_EQ(thinned->size(), voxels.size());
  EXPECT_LT(thinned->size(), cloud.size() / 10);
  // The same voxels: the map gets the same hits.
  EXPECT_EQ(mapVoxels(*thinned, pose()), voxels);
  // The map does not use intensity: a thinned cloud goes without it.
  ASSERT_TRUE(cloud.hasIntensity());
  EXPECT_FALSE(thinned->hasIntensity());
  // Whole clouds keep it.
  CloudLink whole({.map_resolution_m = 0});
  EXPECT_TRUE(whole.prepare(cloud, pose(), 0)->hasIntensity());
}

// Thinned clouds are quantised no finer than a 64th of a voxel; whole ones as asked.
TEST(CloudLink, QuantisesThinnedCloudsToAFractionOfAVoxel) {
  PointCloud cloud;
  cloud.points = {{0, 0, 1}, {10.f, 0, 1}};  // a 10 m cube
  CloudLink link({.map_resolution_m = 0.1});
  // 10 m / (2^b - 1) / 2 <= 0.1 / 64: b = 12 (11 bits leave 2.4 mm).
  EXPECT_EQ(link.quantizationBits(cloud, 14), 12);
  EXPECT_EQ(link.quantizationBits(cloud, 10), 10);
  EXPECT_EQ(CloudLink({.map_resolution_m = 0}).quantizationBits(cloud, 14), 14);
  EXPECT_EQ(bestEncoding({.map_resolution_m = 0.1}), proto::CloudEncoding::kDraco);
  EXPECT_EQ(bestEncoding({.map_resolution_m = 0}), proto::CloudEncoding::kQuantZstd);
}

TEST(CloudLink, AHoveringVehicleSendsOnlyOncePerMaxInterval) {
  CloudLink link({.map_resolution_m = 0.1, .min_new_share = 0.1, .max_interval_s = 1.0});
  const PointCloud cloud = wall();
  int sent = 0;
  for (int i = 0; i < 30; ++i) {  // 3 s over the same wall
    const int64_t stamp = i * kFrameNs;
    if (auto thinned = link.prepare(cloud, pose(), stamp)) {
      link.sent(stamp, 1000, 800);
      ++sent;
    }
  }
  EXPECT_EQ(sent, 3);  // at 0, 1 and 2 s
  EXPECT_EQ(link.stats().skipped_known, 27u);
  EXPECT_EQ(link.stats().offered, 30u);
}

TEST(CloudLink, AnEmptyCloudIsNeverSent) {
  // A descent still above the depth range: no point, so no ray for the map, whatever is due.
  CloudLink link({.map_resolution_m = 0.1, .min_new_share = 0, .max_interval_s = 1.0});
  for (int i = 0; i < 30; ++i) EXPECT_FALSE(link.prepare(PointCloud{}, pose(), i * kFrameNs));
  EXPECT_EQ(link.stats().skipped_empty, 30u);
  EXPECT_EQ(link.stats().sent, 0u);
  // Whole clouds (no thinning) alike.
  CloudLink whole({.map_resolution_m = 0, .min_new_share = 0});
  EXPECT_FALSE(whole.prepare(PointCloud{}, pose(), 0));
  EXPECT_TRUE(whole.prepare(wall(), pose(), 0));
}

TEST(CloudLink, NewCoverageIsSentAtOnce) {
  CloudLink link({.map_resolution_m = 0.1, .min_new_share = 0.1, .max_interval_s = 10.0});
  int sent = 0;
  for (int i = 0; i < 10; ++i) {  // sliding 0.5 m along the wall each frame: half of it new
    const int64_t stamp = i * kFrameNs;
    if (link.prepare(wall(), pose(0.5 * i), stamp)) {
      link.sent(stamp, 1000, 800);
      ++sent;
    }
  }
  EXPECT_EQ(sent, 10);
}

// What a cloud costs on the link in these tests: 3 bytes a point and 200 of message.
uint64_t bytesOf(const PointCloud& cloud) { return 3 * cloud.size() + 200; }

TEST(CloudLink, TheBudgetHoldsTheBytesSentPerSecond) {
  // Every cloud is new (min_new_share 0); the budget allows a tenth of every cloud whole:
  // over 20 s, at most 20 s worth plus the one second saved up at the start.
  CloudLink probe({.map_resolution_m = 0.1});
  const double whole = static_cast<double>(bytesOf(*probe.prepare(wall(), pose(), 0)));
  const double budget_bytes = whole;  // a whole cloud a second: 10 frames a second offered
  CloudLink link(
      {.map_resolution_m = 0.1, .min_new_share = 0, .budget_bits_per_s = 8 * budget_bytes});
  double bytes = 0;
  for (int i = 0; i < 200; ++i) {
    const int64_t stamp = i * kFrameNs;
    if (auto cloud = link.prepare(wall(), pose(), stamp)) {
      link.sent(stamp, bytesOf(*cloud), 3 * cloud->size());
      bytes += static_cast<double>(bytesOf(*cloud));
    }
  }
  EXPECT_LE(bytes, budget_bytes * 21.0);
  EXPECT_GE(bytes, budget_bytes * 15.0);  // and uses most of it
  EXPECT_GT(link.stats().skipped_budget, 150u);
  EXPECT_EQ(link.stats().thinned_budget, 0u);  // a whole cloud a second fits: none thinned
}

TEST(CloudLink, AShortFlightHoldsTheBudgetFromItsStart) {
  // Nothing is saved up before the first cloud: over any first few seconds the bytes sent stay
  // within that many seconds' worth and the first cloud (a bucket that started full let a 5 s
  // drive send 6 s worth).
  CloudLink probe({.map_resolution_m = 0.1});
  const double whole = static_cast<double>(bytesOf(*probe.prepare(wall(), pose(), 0)));
  // Five whole clouds a second of the ten offered.
  CloudLink link({.map_resolution_m = 0.1, .min_new_share = 0, .budget_bits_per_s = 8 * 5 * whole});
  double bytes = 0;
  for (int i = 0; i < 50; ++i) {  // 5 s at 10 Hz
    const int64_t stamp = i * kFrameNs;
    if (auto cloud = link.prepare(wall(), pose(), stamp)) {
      link.sent(stamp, bytesOf(*cloud), 3 * cloud->size());
      bytes += static_cast<double>(bytesOf(*cloud));
    }
    const double seconds = i * 0.1;  // the stamp of this frame
    EXPECT_LE(bytes, whole * (5 * seconds + 1.5)) << "at " << seconds << " s";
  }
  EXPECT_GE(bytes, whole * 5 * 4);  // and it uses the budget
}

// Below a whole cloud per max_interval, clouds go out thinner, each with other voxels: the
// whole view is refreshed every few clouds, and the bytes stay within the budget.
TEST(CloudLink, ATightBudgetThinsCloudsAndCoversTheViewInTurn) {
  CloudLink probe({.map_resolution_m = 0.1});
  const auto whole_cloud = *probe.prepare(wall(), pose(), 0);
  const auto all_voxels = mapVoxels(whole_cloud, pose());
  // A second's budget holds a message and a quarter of the points.
  const double budget_bytes = 200 + 3.0 * static_cast<double>(whole_cloud.size()) / 4;
  CloudLink link({.map_resolution_m = 0.1,
                  .min_new_share = 0,
                  .max_interval_s = 1.0,
                  .budget_bits_per_s = 8 * budget_bytes});
  double bytes = 0;
  std::vector<size_t> sizes;
  std::set<uint64_t> covered;
  for (int i = 0; i < 100; ++i) {  // 10 s over the same wall
    const int64_t stamp = i * kFrameNs;
    if (auto cloud = link.prepare(wall(), pose(), stamp)) {
      link.sent(stamp, bytesOf(*cloud), 3 * cloud->size());
      bytes += static_cast<double>(bytesOf(*cloud));
      sizes.push_back(cloud->size());
      if (sizes.size() >= 2 && sizes.size() <= 6) {  // five thinned clouds
        const auto voxels = mapVoxels(*cloud, pose());
        covered.insert(voxels.begin(), voxels.end());
      }
    }
  }
  // The first cloud goes whole (nothing is known yet of what a point costs) and leaves the
  // bucket three seconds in debt; then about a cloud a second.
  EXPECT_LE(bytes, budget_bytes * 11.0);
  EXPECT_GE(sizes.size(), 6u);
  EXPECT_EQ(link.stats().thinned_budget, sizes.size() - 1);
  // After the first (whole: nothing known of the link's cost yet), about a quarter each.
  EXPECT_LT(sizes.back(), whole_cloud.size() / 3);
  EXPECT_GT(sizes.back(), whole_cloud.size() / 8);
  // Five thinned clouds together cover the wall: other voxels each time.
  EXPECT_GE(covered.size(), all_voxels.size() * 95 / 100);
}

TEST(CloudLink, MemoryOfSentVoxelsStaysBounded) {
  CloudLink link({.map_resolution_m = 0.1, .min_new_share = 0.1, .refresh_s = 2.0});
  for (int i = 0; i < 1000; ++i) {  // 100 s flying along an endless wall
    const int64_t stamp = i * kFrameNs;
    if (link.prepare(wall(), pose(0.2 * i), stamp)) link.sent(stamp, 1000, 800);
  }
  // What 2 s of flight sees, swept once it doubles: a few thousand voxels, not 100 s worth.
  EXPECT_LT(link.memorySize(), 10'000u);
}

TEST(ParseBitRate, ReadsWhatOperatorsWrite) {
  EXPECT_DOUBLE_EQ(*parseBitRate("1Mbit"), 1e6);
  EXPECT_DOUBLE_EQ(*parseBitRate("1mbit"), 1e6);
  EXPECT_DOUBLE_EQ(*parseBitRate("500kbit"), 5e5);
  EXPECT_DOUBLE_EQ(*parseBitRate("2.5M"), 2.5e6);
  EXPECT_DOUBLE_EQ(*parseBitRate("64000"), 64000);
  EXPECT_DOUBLE_EQ(*parseBitRate("250kbit/s"), 2.5e5);
  EXPECT_DOUBLE_EQ(*parseBitRate("off"), 0);
  for (const char* bad : {"", "fast", "1Mbps", "1MB", "-5k", "1 Mbit", "1Tbit", "nan", "1e999"}) {
    EXPECT_FALSE(parseBitRate(bad).ok()) << bad;
  }
  EXPECT_FALSE(parseBitRate("1e308M").ok());  // finite, until scaled
  const auto long_text = parseBitRate(std::string(5000, 'k'));
  ASSERT_FALSE(long_text.ok());
  EXPECT_LT(long_text.error().message.size(), 120u);
}

TEST(CloudLink, RejectsOptionsOutOfRange) {
  EXPECT_THROW(CloudLink({.map_resolution_m = -1}), std::invalid_argument);
  EXPECT_THROW(CloudLink({.min_new_share = 1.5}), std::invalid_argument);
  EXPECT_THROW(CloudLink({.max_interval_s = 0}), std::invalid_argument);
}

}  // namespace
}  // namespace stereomap::link
