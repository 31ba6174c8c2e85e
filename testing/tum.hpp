// TUM RGB-D depth frames as point clouds in the colour camera frame (Freiburg 1 intrinsics,
// depth factor 5000, every `step`-th pixel), each with the ground-truth pose nearest in
// time. Shared by the fusion test and stereomap-bench-fusion.
#pragma once

#include <opencv2/imgcodecs.hpp>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "common/geometry.hpp"
#include "common/point_cloud.hpp"
#include "common/trajectory.hpp"

namespace stereomap::testing {

struct PosedCloud {
  common::PointCloud cloud;
  common::Rigid3 T_map_camera;
};

inline std::vector<PosedCloud> tumDepthFrames(const std::string& dir, size_t count, int step = 4) {
  auto read = common::readTrajectory(dir + "/groundtruth.txt");
  const common::Trajectory truth = read.ok() ? read.value() : common::Trajectory{};
  std::vector<PosedCloud> frames;
  std::ifstream list(dir + "/depth.txt");
  for (std::string line; std::getline(list, line) && frames.size() < count;) {
    if (line.empty() || line[0] == '#' || truth.empty()) continue;
    double stamp;
    std::string file;
    std::istringstream(line) >> stamp >> file;
    const cv::Mat depth = cv::imread(dir + "/" + file, cv::IMREAD_UNCHANGED);
    if (depth.type() != CV_16UC1) continue;
    PosedCloud frame;
    for (int v = 0; v < depth.rows; v += step) {
      for (int u = 0; u < depth.cols; u += step) {
        const double z = depth.at<uint16_t>(v, u) / 5000.0;
        if (z > 0) {
          frame.cloud.points.emplace_back(static_cast<float>((u - 318.6) / 517.3 * z),
                                          static_cast<float>((v - 255.3) / 516.5 * z),
                                          static_cast<float>(z));
        }
      }
    }
    frame.T_map_camera =
        std::min_element(truth.begin(), truth.end(), [&](const auto& a, const auto& b) {
          return std::abs(a.t - stamp) < std::abs(b.t - stamp);
        })->pose;
    frames.push_back(std::move(frame));
  }
  return frames;
}

}  // namespace stereomap::testing
