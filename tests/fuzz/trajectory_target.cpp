// Fuzz target: trajectory files as stereomap-eval and the data-set sources read them
// (common/trajectory: TUM, KITTI poses, with or without a KITTI times.txt). The first byte
// says whether a times.txt follows the file, after a NUL byte.
// A trajectory that is read holds finite stamps and rigid motions, and writing it in its
// format and reading it back gives as many poses.
#include <cmath>

#include "common/trajectory.hpp"
#include "tests/fuzz/fuzz_input.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace stereomap::common;
  const auto& dir = stereomap::fuzz::scratch();
  stereomap::fuzz::FuzzInput in(data, size);
  const bool with_times = in.byte() & 1;
  const auto path = dir.write("trajectory.txt", in.until('\0'));
  std::filesystem::path times;
  if (with_times) times = dir.write("times.txt", in.restText());
  TrajectoryFormat format = TrajectoryFormat::kTum;
  auto read = readTrajectory(path, times, &format);
  if (!read) return 0;
  for (const auto& pose : *read) {
    if (!std::isfinite(pose.t) || !pose.pose.translation.allFinite() ||
        !pose.pose.rotation.coeffs().allFinite()) {
      __builtin_trap();
    }
  }
  const std::string text = format == TrajectoryFormat::kKitti ? kittiText(*read) : tumText(*read);
  auto again = readTrajectory(dir.write("again.txt", text), {}, &format);
  if (!again || again->size() != read->size()) __builtin_trap();
  return 0;
}
