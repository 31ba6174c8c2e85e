#include "proto/cloud_codec.hpp"

#include <gtest/gtest.h>

#include <random>

namespace stereomap::proto {
namespace {

common::PointCloud randomCloud(size_t n, bool with_intensity, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> xy(-5.f, 5.f), z(0.5f, 8.f);
  common::PointCloud cloud;
  for (size_t i = 0; i < n; ++i) {
    cloud.points.emplace_back(xy(rng), xy(rng), z(rng));
    if (with_intensity) cloud.intensity.push_back(static_cast<uint8_t>(rng() % 256));
  }
  return cloud;
}

// Each decoded point must lie within the quantisation bound of a distinct original point
// (the kd-tree coder reorders points, so match by nearest neighbour).
void expectWithinBound(const common::PointCloud& original, const common::PointCloud& decoded,
                       int bits) {
  ASSERT_EQ(decoded.size(), original.size());
  ASSERT_EQ(decoded.hasIntensity(), original.hasIntensity());
  const double bound = maxPositionError(original, bits);
  std::vector<bool> used(original.size(), false);
  double worst = 0;
  for (size_t i = 0; i < decoded.size(); ++i) {
    size_t best = 0;
    double best_error = std::numeric_limits<double>::infinity();
    for (size_t j = 0; j < original.size(); ++j) {
      if (used[j]) continue;
      const double error = (decoded.points[i] - original.points[j]).cwiseAbs().maxCoeff();
      if (error < best_error) best_error = error, best = j;
    }
    used[best] = true;
    worst = std::max(worst, best_error);
    ASSERT_LE(best_error, bound) << "point " << i;
    if (original.hasIntensity()) {
      EXPECT_EQ(decoded.intensity[i], original.intensity[best]);
    }
  }
  // The bound is tight: the worst error is a sizeable fraction of it.
  EXPECT_GT(worst, 0.2 * bound);
}

TEST(CloudCodec, RoundTripWithinQuantisationBound) {
  for (int bits : {8, 11, 14}) {
    SCOPED_TRACE(bits);
    const auto cloud = randomCloud(1500, /*with_intensity=*/false, 7 + bits);
    auto payload = encodeCloud(cloud, {.quantization_bits = bits});
    ASSERT_TRUE(payload.ok()) << payload.error().message;
    auto decoded = decodeCloud(*payload);
    ASSERT_TRUE(decoded.ok()) << decoded.error().message;
    expectWithinBound(cloud, *decoded, bits);
  }
}

// Far from the origin (KITTI's clouds reach 80 m) float rounding adds to the half step; the
// bound says so without slack.
TEST(CloudCodec, TheBoundHoldsFarFromTheOrigin) {
  std::mt19937 rng(17);
  std::uniform_real_distribution<float> x(-40.f, 40.f), y(-3.f, 2.f), z(5.f, 80.f);
  common::PointCloud cloud;
  for (int i = 0; i < 3000; ++i) cloud.points.emplace_back(x(rng), y(rng), z(rng));
  for (int bits : {11, 14, 18}) {
    SCOPED_TRACE(bits);
    auto payload = encodeCloud(cloud, {.quantization_bits = bits});
    ASSERT_TRUE(payload.ok()) << payload.error().message;
    auto decoded = decodeCloud(*payload);
    ASSERT_TRUE(decoded.ok()) << decoded.error().message;
    expectWithinBound(cloud, *decoded, bits);
  }
}

TEST(CloudCodec, IntensityTravelsWithItsPoint) {
  const auto cloud = randomCloud(800, /*with_intensity=*/true, 3);
  auto payload = encodeCloud(cloud);
  ASSERT_TRUE(payload.ok());
  auto decoded = decodeCloud(*payload);
  ASSERT_TRUE(decoded.ok()) << decoded.error().message;
  expectWithinBound(cloud, *decoded, CloudCodecOptions{}.quantization_bits);
}

TEST(CloudCodec, CompressesBelowFourBytesPerPointAt14Bits) {
  const auto cloud = randomCloud(10000, false, 11);
  auto payload = encodeCloud(cloud);
  ASSERT_TRUE(payload.ok());
  EXPECT_LT(static_cast<double>(payload->size()) / cloud.size(), 4.5);
}

TEST(CloudCodec, EmptyCloudRoundTrips) {
  auto payload = encodeCloud({});
  ASSERT_TRUE(payload.ok());
  auto decoded = decodeCloud(*payload);
  ASSERT_TRUE(decoded.ok());
  EXPECT_EQ(decoded->size(), 0u);
}

TEST(CloudCodec, TruncatedAndGarbagePayloadsAreErrors) {
  const auto cloud = randomCloud(2000, false, 5);
  auto payload = encodeCloud(cloud);
  ASSERT_TRUE(payload.ok());
  for (size_t keep : {size_t{3}, payload->size() / 2, payload->size() - 1}) {
    std::vector<uint8_t> truncated(payload->begin(), payload->begin() + keep);
    auto decoded = decodeCloud(truncated);
    EXPECT_FALSE(decoded.ok()) << "kept " << keep << " bytes";
    if (!decoded.ok()) {
      EXPECT_NE(decoded.error().message.find("Draco"), std::string::npos);
    }
  }
  std::vector<uint8_t> garbage(500);
  for (size_t i = 0; i < garbage.size(); ++i) garbage[i] = static_cast<uint8_t>(i * 37);
  EXPECT_FALSE(decodeCloud(garbage).ok());
}

TEST(CloudCodec, RejectsBadInput) {
  common::PointCloud cloud = randomCloud(10, false, 1);
  cloud.points[3].x() = std::numeric_limits<float>::quiet_NaN();
  EXPECT_FALSE(encodeCloud(cloud).ok());
  EXPECT_FALSE(encodeCloud(randomCloud(10, false, 1), {.quantization_bits = 0}).ok());
}

}  // namespace
}  // namespace stereomap::proto
