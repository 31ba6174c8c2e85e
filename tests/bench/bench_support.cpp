#include "tests/bench/bench_support.hpp"

#include <fstream>
#include <sstream>
#include <stdexcept>

#include "onboard/pipeline/pipeline.hpp"
#include "onboard/sim/sim_source.hpp"
#include "onboard/stereo/depth.hpp"

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

}  // namespace stereomap::bench
