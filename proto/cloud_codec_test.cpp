#include "proto/cloud_codec.hpp"

#include <gtest/gtest.h>

#include <cstring>
#include <limits>
#include <random>

namespace stereomap::proto {
namespace {

using common::Result;

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
// (Draco's kd-tree coder reorders points, so match by nearest neighbour).
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

constexpr CloudEncoding kQuantising[] = {CloudEncoding::kDraco, CloudEncoding::kQuantZstd};

Result<common::PointCloud> roundTrip(const common::PointCloud& cloud,
                                     const CloudCodecOptions& options) {
  auto payload = encodeCloud(cloud, options);
  if (!payload) return payload.error();
  return decodeCloud(*payload,
                     {options.encoding, static_cast<uint32_t>(cloud.size()), cloud.hasIntensity()});
}

class EachEncoding : public ::testing::TestWithParam<CloudEncoding> {};
INSTANTIATE_TEST_SUITE_P(CloudCodec, EachEncoding, ::testing::ValuesIn(kQuantising),
                         [](const auto& info) { return std::string(encodingName(info.param)); });

TEST_P(EachEncoding, RoundTripWithinQuantisationBound) {
  for (int bits : {8, 11, 14}) {
    SCOPED_TRACE(bits);
    const auto cloud = randomCloud(1500, /*with_intensity=*/false, 7 + bits);
    auto decoded = roundTrip(cloud, {.encoding = GetParam(), .quantization_bits = bits});
    ASSERT_TRUE(decoded.ok()) << decoded.error().message;
    expectWithinBound(cloud, *decoded, bits);
  }
}

// Far from the origin (KITTI's clouds reach 80 m) float rounding adds to the half step; the
// bound says so without slack.
TEST_P(EachEncoding, TheBoundHoldsFarFromTheOrigin) {
  std::mt19937 rng(17);
  std::uniform_real_distribution<float> x(-40.f, 40.f), y(-3.f, 2.f), z(5.f, 80.f);
  common::PointCloud cloud;
  for (int i = 0; i < 3000; ++i) cloud.points.emplace_back(x(rng), y(rng), z(rng));
  for (int bits : {11, 14, 18, 30}) {
    SCOPED_TRACE(bits);
    auto decoded = roundTrip(cloud, {.encoding = GetParam(), .quantization_bits = bits});
    ASSERT_TRUE(decoded.ok()) << decoded.error().message;
    if (bits < 30) expectWithinBound(cloud, *decoded, bits);
  }
}

TEST_P(EachEncoding, IntensityTravelsWithItsPoint) {
  const auto cloud = randomCloud(800, /*with_intensity=*/true, 3);
  auto decoded = roundTrip(cloud, {.encoding = GetParam()});
  ASSERT_TRUE(decoded.ok()) << decoded.error().message;
  expectWithinBound(cloud, *decoded, CloudCodecOptions{}.quantization_bits);
}

TEST_P(EachEncoding, EmptyAndSinglePointCloudsRoundTrip) {
  auto decoded = roundTrip({}, {.encoding = GetParam()});
  ASSERT_TRUE(decoded.ok()) << decoded.error().message;
  EXPECT_EQ(decoded->size(), 0u);
  common::PointCloud one;
  one.points.emplace_back(1.5f, -2.f, 4.f);
  decoded = roundTrip(one, {.encoding = GetParam()});
  ASSERT_TRUE(decoded.ok()) << decoded.error().message;
  ASSERT_EQ(decoded->size(), 1u);
  EXPECT_LE((decoded->points[0] - one.points[0]).cwiseAbs().maxCoeff(), 1e-6);
}

TEST_P(EachEncoding, TruncatedAndGarbagePayloadsAreErrors) {
  const auto cloud = randomCloud(2000, true, 5);
  const CloudPayloadInfo info{GetParam(), 2000, true};
  auto payload = encodeCloud(cloud, {.encoding = GetParam()});
  ASSERT_TRUE(payload.ok());
  for (size_t keep : {size_t{3}, size_t{30}, payload->size() / 2, payload->size() - 1}) {
    std::vector<uint8_t> truncated(payload->begin(), payload->begin() + keep);
    EXPECT_FALSE(decodeCloud(truncated, info).ok()) << "kept " << keep << " bytes";
  }
  std::vector<uint8_t> garbage(500);
  for (size_t i = 0; i < garbage.size(); ++i) garbage[i] = static_cast<uint8_t>(i * 37);
  EXPECT_FALSE(decodeCloud(garbage, info).ok());
  // Every single flipped byte is an error or a cloud that keeps the message's shape (each
  // byte of the headers, every 7th after). Draco once filled 24 GiB on byte 14.
  for (size_t i = 0; i < payload->size(); i += i < 64 ? 1 : 7) {
    auto flipped = *payload;
    flipped[i] ^= 0x5a;
    auto decoded = decodeCloud(flipped, info);
    if (decoded.ok() && GetParam() == CloudEncoding::kQuantZstd) {
      EXPECT_EQ(decoded->size(), 2000u);
      EXPECT_TRUE(decoded->hasIntensity());
    }
  }
}

TEST_P(EachEncoding, APointCountOtherThanTheMessagesIsAConflict) {
  const auto cloud = randomCloud(50, false, 2);
  auto payload = encodeCloud(cloud, {.encoding = GetParam()});
  ASSERT_TRUE(payload.ok());
  for (uint32_t count : {0u, 49u, 51u, 1u << 30}) {
    auto decoded = decodeCloud(*payload, {GetParam(), count, false});
    ASSERT_FALSE(decoded.ok()) << count;
    EXPECT_EQ(decoded.error().code, common::ErrorCode::kConflict) << decoded.error().message;
  }
}

// The quantised zstd payload states its count, flags and grid; each must agree with the
// message and stay finite, and the frame may not claim more bytes than the points need.
TEST(QuantZstd, RejectsHeadersThatDisagreeWithTheMessage) {
  const auto cloud = randomCloud(100, false, 9);
  auto payload = encodeCloud(cloud, {.encoding = CloudEncoding::kQuantZstd});
  ASSERT_TRUE(payload.ok());
  const CloudPayloadInfo info{CloudEncoding::kQuantZstd, 100, false};
  ASSERT_TRUE(decodeCloud(*payload, info).ok());
  EXPECT_FALSE(decodeCloud(*payload, {CloudEncoding::kQuantZstd, 101, false}).ok());
  EXPECT_FALSE(decodeCloud(*payload, {CloudEncoding::kQuantZstd, 100, true}).ok());
  auto edited = [&](size_t at, uint8_t value) {
    auto copy = *payload;
    copy[at] = value;
    return decodeCloud(copy, info);
  };
  EXPECT_FALSE(edited(0, 2).ok());   // version
  EXPECT_FALSE(edited(1, 0).ok());   // bits
  EXPECT_FALSE(edited(1, 31).ok());  // bits
  EXPECT_FALSE(edited(2, 4).ok());   // flags
  auto withValue = [&](size_t at, auto value) {
    auto copy = *payload;
    std::memcpy(copy.data() + at, &value, sizeof(value));
    return decodeCloud(copy, info);
  };
  EXPECT_FALSE(withValue(8, std::numeric_limits<float>::quiet_NaN()).ok());  // origin x
  EXPECT_FALSE(withValue(12, std::numeric_limits<float>::max()).ok());       // far corner overflows
  EXPECT_FALSE(withValue(20, std::numeric_limits<double>::quiet_NaN()).ok());  // step
  EXPECT_FALSE(withValue(20, -0.01).ok());
  EXPECT_FALSE(withValue(20, 1e300).ok());
  auto trailing = *payload;
  trailing.push_back(0);
  EXPECT_FALSE(decodeCloud(trailing, info).ok());
  // A point count beyond what the frame holds is refused before anything is allocated.
  auto counted = *payload;
  counted[7] = 0x10;  // 268 M points
  EXPECT_FALSE(decodeCloud(counted, {CloudEncoding::kQuantZstd, 100 + (0x10u << 24), false}).ok());
}

// Draco sizes a buffer per attribute (points x components) before it reads a point: only
// positions and the message's intensity get that far. A 130-byte payload of 20 attributes of
// 255 floats would otherwise ask for 40 GB at the server's point limit.
TEST(DracoPayload, HoldsOnlyPositionsAndTheMessagesIntensity) {
  const auto cloud = randomCloud(100, true, 8);
  auto payload = encodeCloud(cloud, {.encoding = CloudEncoding::kDraco});
  ASSERT_TRUE(payload.ok());
  const CloudPayloadInfo info{CloudEncoding::kDraco, 100, true};
  ASSERT_TRUE(decodeCloud(*payload, info).ok());
  EXPECT_FALSE(decodeCloud(*payload, {CloudEncoding::kDraco, 100, false}).ok());
  auto edited = [&](size_t at, uint8_t value) {
    auto copy = *payload;
    copy[at] = value;
    return decodeCloud(copy, info);
  };
  EXPECT_FALSE(edited(15, 2).ok());    // two attribute decoders
  EXPECT_FALSE(edited(16, 20).ok());   // twenty attributes
  EXPECT_FALSE(edited(18, 10).ok());   // positions as 64-bit floats
  EXPECT_FALSE(edited(19, 255).ok());  // 255 components
  EXPECT_FALSE(edited(24, 3).ok());    // intensity in three components
}

TEST(QuantZstd, KeepsThePointsOrder) {
  const auto cloud = randomCloud(500, true, 4);
  auto decoded = roundTrip(cloud, {.encoding = CloudEncoding::kQuantZstd});
  ASSERT_TRUE(decoded.ok());
  const double bound = maxPositionError(cloud, CloudCodecOptions{}.quantization_bits);
  for (size_t i = 0; i < cloud.size(); ++i) {
    ASSERT_LE((decoded->points[i] - cloud.points[i]).cwiseAbs().maxCoeff(), bound) << i;
    ASSERT_EQ(decoded->intensity[i], cloud.intensity[i]);
  }
}

TEST(RawCloud, RoundTripsExactlyAndChecksItsSize) {
  const auto cloud = randomCloud(300, true, 6);
  auto decoded = roundTrip(cloud, {.encoding = CloudEncoding::kRawF32});
  ASSERT_TRUE(decoded.ok());
  EXPECT_EQ(decoded->points, cloud.points);
  EXPECT_EQ(decoded->intensity, cloud.intensity);
  auto payload = encodeCloud(cloud, {.encoding = CloudEncoding::kRawF32});
  EXPECT_FALSE(decodeCloud(*payload, {CloudEncoding::kRawF32, 300, false}).ok());
  EXPECT_FALSE(decodeCloud(*payload, {CloudEncoding::kRawF32, 301, true}).ok());
  auto bad = *payload;
  const float nan = std::numeric_limits<float>::quiet_NaN();
  std::memcpy(bad.data() + 12 * 7, &nan, 4);
  EXPECT_FALSE(decodeCloud(bad, {CloudEncoding::kRawF32, 300, true}).ok());
}

TEST(CloudCodec, DracoCompressesBelowFourAndAHalfBytesPerPointAt14Bits) {
  const auto cloud = randomCloud(10000, false, 11);
  auto payload = encodeCloud(cloud, {.encoding = CloudEncoding::kDraco});
  ASSERT_TRUE(payload.ok());
  EXPECT_LT(static_cast<double>(payload->size()) / cloud.size(), 4.5);
}

TEST(CloudCodec, NamesRoundTrip) {
  for (auto encoding : {CloudEncoding::kDraco, CloudEncoding::kQuantZstd, CloudEncoding::kRawF32}) {
    EXPECT_EQ(parseEncoding(encodingName(encoding)), encoding);
  }
  EXPECT_FALSE(parseEncoding("Draco").has_value());
}

TEST(CloudCodec, RejectsBadInput) {
  common::PointCloud cloud = randomCloud(10, false, 1);
  cloud.points[3].x() = std::numeric_limits<float>::quiet_NaN();
  for (auto encoding : {CloudEncoding::kDraco, CloudEncoding::kQuantZstd, CloudEncoding::kRawF32}) {
    EXPECT_FALSE(encodeCloud(cloud, {.encoding = encoding}).ok());
  }
  EXPECT_FALSE(encodeCloud(randomCloud(10, false, 1), {.quantization_bits = 0}).ok());
  EXPECT_FALSE(encodeCloud(randomCloud(10, false, 1), {.zstd_level = 0}).ok());
  EXPECT_FALSE(encodeCloud(randomCloud(10, false, 1), {.draco_speed = 11}).ok());
}

}  // namespace
}  // namespace stereomap::proto
