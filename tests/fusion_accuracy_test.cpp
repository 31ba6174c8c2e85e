// Fusion accuracy on the simulator at 0.05 m (issue 5): the fast stereo preset's clouds of
// scripted flights through three seeded rooms, fused with the fast insertion, compared with
// the rooms' exact geometry. Figures are reported in docs/BENCHMARKS.md.
#include <gtest/gtest.h>

#include <cstdio>
#include <string>

#include "tests/support/sim_map_accuracy.hpp"

namespace stereomap::testing {
namespace {

SimMapAccuracy measure(uint32_t room, const std::string& camera = "clean") {
  SimMapSetup setup;  // the fast preset and the vehicle's depth step, 0.05 m
  setup.room = room;
  setup.camera = *sim::CameraModel::preset(camera);
  const SimMapAccuracy result = measureSimMap(setup);
  std::printf(
      "room %u, %s camera, fusion accuracy at %.2f m: precision %.4f (%zu voxels), recall %.4f "
      "(%zu seen), free space %.4f (%zu samples), image noise %.2f (level %d)\n",
      room, camera.c_str(), setup.map.resolution, result.precision, result.occupied, result.recall,
      result.seen, result.free_space, result.free_samples, result.noise_sigma, result.level);
  return result;
}

class FusionAccuracy : public ::testing::TestWithParam<uint32_t> {};

TEST_P(FusionAccuracy, SimFlightAtFiveCentimetres) {
  const SimMapAccuracy a = measure(GetParam());
  RecordProperty("precision", std::to_string(a.precision));
  RecordProperty("recall", std::to_string(a.recall));
  RecordProperty("free_space", std::to_string(a.free_space));
  // Measured on rooms 1-3: precision 0.965-0.969, recall 0.943-0.954, free space 0.997
  // (docs/BENCHMARKS.md). The issue asks >= 0.95, >= 0.90 and >= 0.95.
  EXPECT_GE(a.precision, 0.95);
  EXPECT_GE(a.recall, 0.93);
  EXPECT_GE(a.free_space, 0.99);
}

INSTANTIATE_TEST_SUITE_P(Rooms, FusionAccuracy, ::testing::Values(1u, 2u, 3u));

// Issue 16: noise kept out of the map under the typical and poor cameras (the depth step finds
// them noisy by itself). Measured per room (stereomap-bench-map, docs/BENCHMARKS.md): typical
// precision 0.949-0.957, recall 0.896-0.911, free 0.992-0.993; poor precision 0.922-0.936,
// recall 0.850-0.863, free 0.987-0.988 (means 0.952 / 0.904 and 0.928 / 0.858 against the
// goals 0.95 / 0.90 and 0.90 / 0.80). Without the noise handling: typical precision 0.67, poor
// 0.54. The poor camera's free space was 0.992 with full rows (16 ms per frame): matching rows
// in pairs costs it 0.004 for 8 ms and +0.018 precision.
struct NoisyCamera {
  const char* camera;
  int level;  // the depth step's noise level expected
  double precision, recall, free_space;
};

class NoiseStaysOutOfTheMap : public ::testing::TestWithParam<NoisyCamera> {};

TEST_P(NoiseStaysOutOfTheMap, OnEveryRoom) {
  const NoisyCamera& expected = GetParam();
  for (const uint32_t room : {1u, 2u, 3u}) {
    const SimMapAccuracy a = measure(room, expected.camera);
    EXPECT_EQ(a.level, expected.level);
    EXPECT_GE(a.precision, expected.precision);
    EXPECT_GE(a.recall, expected.recall);
    EXPECT_GE(a.free_space, expected.free_space);
  }
}

INSTANTIATE_TEST_SUITE_P(Cameras, NoiseStaysOutOfTheMap,
                         ::testing::Values(NoisyCamera{"typical", 0, 0.945, 0.89, 0.99},
                                           NoisyCamera{"poor", 1, 0.915, 0.845, 0.985}),
                         [](const auto& info) { return std::string(info.param.camera); });

}  // namespace
}  // namespace stereomap::testing
