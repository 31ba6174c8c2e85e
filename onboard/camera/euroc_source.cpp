// euroc:DIR, EuRoC's ASL layout (mav0/cam0, mav0/cam1 with sensor.yaml, the ground truth).
#include "onboard/camera/dataset_source.hpp"

#include <algorithm>
#include <fstream>
#include <sstream>

#include "onboard/camera/detail/recorded_source.hpp"

namespace stereomap::camera {

namespace fs = std::filesystem;
using common::Rigid3;
using detail::Clock;
using detail::FrameFiles;

namespace {

struct Stamped {
  int64_t stamp_ns;
  Rigid3 T;
};

// EuRoC ground truth (timestamp, p xyz, q wxyz, ...) interpolated at `stamp_ns`.
std::optional<Rigid3> interpolate(const std::vector<Stamped>& track, int64_t stamp_ns) {
  if (track.empty() || stamp_ns < track.front().stamp_ns || stamp_ns > track.back().stamp_ns) {
    return std::nullopt;
  }
  auto after = std::lower_bound(track.begin(), track.end(), stamp_ns,
                                [](const Stamped& s, int64_t t) { return s.stamp_ns < t; });
  if (after->stamp_ns == stamp_ns || after == track.begin()) return after->T;
  const auto before = after - 1;
  const double a = static_cast<double>(stamp_ns - before->stamp_ns) /
                   static_cast<double>(after->stamp_ns - before->stamp_ns);
  return common::interpolate(before->T, after->T, a);
}

}  // namespace

common::Result<std::unique_ptr<FrameSource>> openEuroc(const fs::path& dir,
                                                       const DatasetOptions& options) {
  const fs::path mav0 = fs::is_directory(dir / "mav0") ? dir / "mav0" : dir;
  for (const char* needed : {"cam0/data.csv", "cam1/data.csv"}) {
    if (!fs::exists(mav0 / needed)) {
      return common::makeError(
          common::ErrorCode::kNotFound,
          "euroc:" + dir.string() + ": no mav0/" + needed + " (expected EuRoC's ASL layout)");
    }
  }
  auto calibration = detail::calibrationOr(options, [&] {
    return readEurocCalibration(mav0 / "cam0/sensor.yaml", mav0 / "cam1/sensor.yaml");
  });
  if (!calibration) return calibration.error();

  std::vector<Stamped> truth;
  if (std::ifstream in(mav0 / "state_groundtruth_estimate0/data.csv"); in) {
    for (std::string line; std::getline(in, line);) {
      if (line.empty() || line[0] == '#') continue;
      std::replace(line.begin(), line.end(), ',', ' ');
      std::istringstream numbers(line);
      int64_t t;
      double x, y, z, qw, qx, qy, qz;
      if (numbers >> t >> x >> y >> z >> qw >> qx >> qy >> qz) {
        truth.push_back({t, {common::Quat(qw, qx, qy, qz).normalized(), common::Vec3(x, y, z)}});
      }
    }
  }
  std::vector<FrameFiles> frames;
  std::ifstream csv(mav0 / "cam0/data.csv");
  for (std::string line; std::getline(csv, line);) {
    if (line.empty() || line[0] == '#') continue;
    const size_t comma = line.find(',');
    if (comma == std::string::npos) continue;
    std::string name = line.substr(comma + 1);
    name.erase(name.find_last_not_of(" \r") + 1);
    FrameFiles f{mav0 / "cam0/data" / name, mav0 / "cam1/data" / name};
    f.stamp_ns = std::stoll(line.substr(0, comma));
    f.T_map_body = interpolate(truth, f.stamp_ns);
    frames.push_back(std::move(f));
  }
  return detail::makeRecorded("euroc:" + dir.string(), std::move(frames), *calibration,
                              calibration->T_body_left, Clock::kDataSet, options);
}

}  // namespace stereomap::camera
