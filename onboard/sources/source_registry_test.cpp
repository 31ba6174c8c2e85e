#include "onboard/sources/source_registry.hpp"

#include <gtest/gtest.h>

#include <set>

namespace stereomap::sources {
namespace {

TEST(SourceRegistry, EverySourceIsListedOnceWithItsHelp) {
  std::set<std::string> prefixes;
  for (const auto& kind : sourceKinds()) {
    EXPECT_TRUE(prefixes.insert(kind.prefix).second) << kind.prefix;
    EXPECT_FALSE(kind.help.empty()) << kind.prefix;
    EXPECT_EQ(kind.usage.rfind(kind.prefix, 0), 0u) << kind.usage;
    EXPECT_NE(sourcesHelp().find(kind.usage + " (" + kind.help + ")"), std::string::npos);
  }
  EXPECT_EQ(prefixes,
            (std::set<std::string>{"sim", "sim:deck", "kitti:", "euroc:", "folder:", "camera:"}));
}

TEST(SourceRegistry, OpensTheSimulatorsWithTheirOptions) {
  auto room = openSource("sim", {.max_frames = 2, .seed = 3, .noise_sigma = 4.0});
  ASSERT_TRUE(room) << room.error().message;
  EXPECT_FALSE(room->prefer_ground_truth);
  int frames = 0;
  while (room->source->next()) ++frames;
  EXPECT_EQ(frames, 2);
  auto deck = openSource("sim:deck", {.max_frames = 1});
  ASSERT_TRUE(deck) << deck.error().message;
  ASSERT_TRUE(deck->prefer_ground_truth);  // the deck moves with the scene
  EXPECT_NE(deck->prefer_ground_truth->find("GPS/INS"), std::string::npos);
}

TEST(SourceRegistry, ASpecNoSourceTakesIsAClearError) {
  auto expectError = [](const std::string& spec, common::ErrorCode code,
                        const std::string& needle) {
    auto opened = openSource(spec, {});
    ASSERT_FALSE(opened) << spec;
    EXPECT_EQ(opened.error().code, code) << spec;
    EXPECT_NE(opened.error().message.find(needle), std::string::npos) << opened.error().message;
  };
  using common::ErrorCode;
  expectError("tape:/x", ErrorCode::kInvalidArgument,
              "unknown source 'tape:/x': use sim, sim:deck, kitti:DIR, euroc:DIR, folder:DIR, "
              "camera:LEFT,RIGHT");
  expectError("sim:room", ErrorCode::kInvalidArgument, "unknown source 'sim:room'");
  expectError("kitti", ErrorCode::kInvalidArgument, "needs a location: kitti:DIR");
  expectError("kitti:", ErrorCode::kInvalidArgument, "needs a location: kitti:DIR");
  expectError("", ErrorCode::kInvalidArgument, "unknown source ''");
  // The source's own errors come through as they are.
  expectError("kitti:/nonexistent", ErrorCode::kNotFound, "kitti:/nonexistent: no image_0/");
  expectError("camera:0,1", ErrorCode::kInvalidArgument, "needs --calib");
}

}  // namespace
}  // namespace stereomap::sources
