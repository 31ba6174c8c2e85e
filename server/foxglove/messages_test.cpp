#include "server/foxglove/messages.hpp"

#include <gtest/gtest.h>

namespace stereomap::foxglove {
namespace {

// Protobuf's wire format by hand for one small message (the decoding by Foxglove's schemas
// with protobufjs is tests/interop's).
TEST(Foxglove, AFrameTransformIsProtobufsBytes) {
  common::Rigid3 T;
  T.translation = common::Vec3(1.0, 0.0, 0.0);
  const std::string bytes = frameTransform(1500000000, "map", "d1", T);
  const std::string expected =
      std::string("\x0a\x08\x08\x01\x10\x80\xca\xb5\xee\x01", 10) +  // timestamp 1 s 5e8 ns
      "\x12\x03map" +
      "\x1a\x02"
      "d1" +
      std::string("\x22\x09\x09\x00\x00\x00\x00\x00\x00\xf0\x3f", 11) +  // translation x 1.0
      std::string("\x2a\x09\x21\x00\x00\x00\x00\x00\x00\xf0\x3f", 11);   // rotation w 1.0
  EXPECT_EQ(bytes, expected);
}

TEST(Foxglove, EveryDescriptorSetNamesItsMessage) {
  for (Schema schema : {Schema::kFrameTransform, Schema::kPosesInFrame, Schema::kPointCloud,
                        Schema::kCompressedPointCloud, Schema::kSceneUpdate, Schema::kGrid}) {
    const std::string_view name = schemaName(schema);
    const std::string_view descriptors = descriptorSet(schema);
    ASSERT_GT(descriptors.size(), 100u) << name;
    const std::string message(name.substr(name.find('.') + 1));
    EXPECT_NE(descriptors.find(message), std::string_view::npos) << name;
    EXPECT_NE(descriptors.find("google/protobuf/timestamp.proto"), std::string_view::npos)
        << name << ": its imports are included";
  }
}

TEST(Foxglove, APointCloudCarriesTwelveBytesAPoint) {
  common::PointCloud cloud;
  for (int i = 0; i < 1000; ++i) cloud.points.emplace_back(i, 2.f * i, 3.f * i);
  const std::string bytes = pointCloud(0, "map", {}, cloud);
  EXPECT_GT(bytes.size(), 12000u);
  EXPECT_LT(bytes.size(), 12000u + 200);
  EXPECT_NE(bytes.find(std::string(reinterpret_cast<const char*>(cloud.points[7].data()), 12)),
            std::string::npos);
}

TEST(Foxglove, Base64IsRfc4648s) {  // its test vectors (section 10)
  EXPECT_EQ(base64(""), "");
  EXPECT_EQ(base64("f"), "Zg==");
  EXPECT_EQ(base64("fo"), "Zm8=");
  EXPECT_EQ(base64("foo"), "Zm9v");
  EXPECT_EQ(base64("foob"), "Zm9vYg==");
  EXPECT_EQ(base64("fooba"), "Zm9vYmE=");
  EXPECT_EQ(base64("foobar"), "Zm9vYmFy");
  EXPECT_EQ(base64(std::string("\xff\xfe\x00", 3)), "//4A");
}

TEST(Foxglove, ASceneUpdateCarriesDeletionsBeforeEntities) {
  const std::string none = sceneUpdate(5, "map", {});
  const std::string deleting = sceneUpdate(5, "map", {}, {"tile/1_2_3"});
  EXPECT_GT(deleting.size(), none.size());
  EXPECT_EQ(deleting[0], 0x0a);  // field 1 (deletions), length-delimited
  EXPECT_NE(deleting.find("tile/1_2_3"), std::string::npos);
}

}  // namespace
}  // namespace stereomap::foxglove
