#include "onboard/sources/source_registry.hpp"

#include <gtest/gtest.h>

#include <cstdlib>
#include <set>
#include <tuple>

#include "onboard/sim/flight.hpp"

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
  EXPECT_EQ(prefixes, (std::set<std::string>{"sim", "sim:deck", "sim:hall",
                                             "kitti:", "euroc:", "folder:", "camera:"}));
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

// --start: the room's flight begins that far into its loop, the stamps at the first frame.
TEST(SourceRegistry, TheSimulatorsStartLaterInTheirFlight) {
  auto from_start = openSource("sim", {.max_frames = 1});
  auto later = openSource("sim", {.max_frames = 1, .start_s = 10});
  ASSERT_TRUE(from_start && later);
  const auto first = from_start->source->next();
  const auto first_later = later->source->next();
  ASSERT_TRUE(first && first_later);
  const sim::Flight flight;
  EXPECT_LT((first_later->T_map_body->translation - flight.T_map_body(10).translation).norm(),
            1e-12);
  EXPECT_GT((first_later->T_map_body->translation - first->T_map_body->translation).norm(), 1.0);
  EXPECT_LT(std::abs(first_later->stamp_ns - first->stamp_ns), 1'000'000'000);

  for (const auto& [spec, start, needle] :
       {std::tuple{"sim", 41.0, "--start 41: the sim's loop lasts 40 s; start from 0 to 40 s"},
        std::tuple{"sim:deck", 61.0, "--start 61: the descent lasts 60 s"},
        std::tuple{"kitti:/nonexistent", 5.0, "--start: only the simulators"}}) {
    auto opened = openSource(spec, {.start_s = start});
    ASSERT_FALSE(opened) << spec;
    EXPECT_EQ(opened.error().code, common::ErrorCode::kInvalidArgument);
    EXPECT_NE(opened.error().message.find(needle), std::string::npos) << opened.error().message;
  }
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
              "unknown source 'tape:/x': use sim, sim:hall, sim:deck, kitti:DIR, euroc:DIR, "
              "folder:DIR, "
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
