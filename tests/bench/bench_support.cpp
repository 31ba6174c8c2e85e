#include "tests/bench/bench_support.hpp"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <random>
#include <sstream>
#include <stdexcept>

#include "onboard/pipeline/pipeline.hpp"
#include "onboard/sim/sim_source.hpp"
#include "onboard/stereo/depth.hpp"
#include "server/fusion/occupancy_map.hpp"
#include "tests/support/timing.hpp"

namespace stereomap::bench {

namespace fs = std::filesystem;

double residentMegabytes() {
  std::ifstream status("/proc/self/status");
  for (std::string line; std::getline(status, line);) {
    if (line.rfind("VmRSS:", 0) == 0) return std::stod(line.substr(6)) / 1024.0;
  }
  return 0;
}

std::vector<proto::CloudFrameMsg> simFrames(size_t count) {
  sim::SimSource source({.seed = 1, .rate_hz = 10.0, .max_frames = count, .start_stamp_ns = 1});
  pipeline::PipelineOptions options;
  const stereo::StereoMatcher matcher(options.stereo.matcher);
  std::vector<proto::CloudFrameMsg> frames;
  while (auto frame = source.next()) {
    const auto cloud =
        stereo::cloudFromDisparity(matcher.compute(frame->left, frame->right), frame->left,
                                   source.camera(), options.stereo.cloud);
    const common::Rigid3 T_map_camera =
        frame->T_map_body.value() * frame->T_body_camera.value_or(common::Rigid3{});
    frames.push_back(pipeline::makeCloudFrameMsg(options, options.codec, frames.size(),
                                                 frame->stamp_ns, T_map_camera, cloud,
                                                 options.stereo.cloud.max_range_m)
                         .value());
  }
  return frames;
}

std::string campusSnapshot(const fs::path& path, size_t& octomap_bytes) {
  std::ifstream in(path, std::ios::binary);
  auto map = fusion::OccupancyMap::load(in);
  if (!map) throw std::runtime_error(path.string() + ": " + map.error().message);
  octomap_bytes = (*map)->memoryBytes();
  std::ostringstream ot;
  (*map)->writeFull(ot);
  return ot.str();
}

std::shared_ptr<core::Session> campusSession(core::MapServer& server, const std::string& id,
                                             const std::string& ot) {
  auto session = server.createSession(id, 0.2, false).value();
  std::istringstream in(ot);
  if (auto restored = session->restore(in, 0); !restored) {
    throw std::runtime_error("campus: " + restored.error().message);
  }
  return session;
}

Frame frustumFrame() {
  Frame frame;
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> jitter(-0.15, 0.15);
  const double h = 65.0 * M_PI / 180, v = 50.0 * M_PI / 180;
  for (int r = 0; r < 200; ++r) {
    for (int c = 0; c < 250; ++c) {
      const double az = (c / 249.0 - 0.5) * h, el = (r / 199.0 - 0.5) * v;
      const double range =
          std::clamp(6.0 + 3.5 * std::sin(3 * az) * std::cos(2 * el) + jitter(rng), 2.0, 10.0);
      const common::Vec3 dir(std::cos(el) * std::cos(az), std::cos(el) * std::sin(az),
                             std::sin(el));
      frame.cloud.points.push_back((dir * range).cast<float>());
    }
  }
  return frame;
}

InsertionComparison compareInsertion(const std::vector<Frame>& frames, double resolution,
                                     double max_range, int runs, int stock_runs, unsigned threads) {
  using fusion::OccupancyMap;
  auto build = [&](OccupancyMap::Insertion insertion, OccupancyMap* keep) {
    OccupancyMap map({.resolution = resolution, .insertion = insertion, .threads = threads});
    for (const auto& f : frames) map.insertCloud(f.cloud, f.pose, max_range);
    if (keep != nullptr) return compareClassification(map, *keep).fraction();
    return 0.0;
  };
  InsertionComparison result;
  result.stock_ms =
      testing::medianMs(stock_runs, [&] { build(OccupancyMap::Insertion::kOctomap, nullptr); });
  result.fast_ms = testing::medianMs(runs, [&] { build(OccupancyMap::Insertion::kFast, nullptr); });
  OccupancyMap stock({.resolution = resolution, .insertion = OccupancyMap::Insertion::kOctomap});
  for (const auto& f : frames) stock.insertCloud(f.cloud, f.pose, max_range);
  result.agreement = build(OccupancyMap::Insertion::kFast, &stock);
  return result;
}

}  // namespace stereomap::bench
