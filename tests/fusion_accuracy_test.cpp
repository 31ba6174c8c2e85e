// Fusion accuracy on the simulator at 0.05 m (issue 5): the fast stereo preset's clouds of
// scripted flights through three seeded rooms, fused with the fast insertion, compared with
// the rooms' exact geometry. Figures are reported in docs/BENCHMARKS.md.
#include <gtest/gtest.h>

#include <cstdio>

#include "tests/support/sim_map_accuracy.hpp"

namespace stereomap::testing {
namespace {

SimMapAccuracy measure(uint32_t room) {
  const SimMapSetup setup{.room = room};  // the fast preset, clean images, 0.05 m
  const SimMapAccuracy result = measureSimMap(setup);
  std::printf(
      "room %u, fusion accuracy at %.2f m: precision %.4f (%zu voxels), recall %.4f (%zu seen), "
      "free space %.4f (%zu samples)\n",
      room, setup.map.resolution, result.precision, result.occupied, result.recall, result.seen,
      result.free_space, result.free_samples);
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

}  // namespace
}  // namespace stereomap::testing
