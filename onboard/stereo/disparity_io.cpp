#include "onboard/stereo/disparity_io.hpp"

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <fstream>

namespace stereomap::stereo {

namespace fs = std::filesystem;
using common::ErrorCode;
using common::makeError;

common::Status writeDisparityPng(const fs::path& path, const cv::Mat& disparity_px) {
  CV_Assert(disparity_px.type() == CV_32FC1);
  cv::Mat encoded(disparity_px.size(), CV_16UC1);
  for (int v = 0; v < disparity_px.rows; ++v) {
    const float* in = disparity_px.ptr<float>(v);
    uint16_t* out = encoded.ptr<uint16_t>(v);
    for (int u = 0; u < disparity_px.cols; ++u) {
      const float d = in[u];
      // 0 means invalid, so a valid disparity of 0 (infinity) becomes the smallest step.
      out[u] =
          !(d >= 0) ? 0 : static_cast<uint16_t>(std::clamp(std::lround(d * 256.0f), 1L, 65535L));
    }
  }
  try {
    if (!cv::imwrite(path.string(), encoded)) {
      return makeError(ErrorCode::kIo, path.string() + ": cannot write the disparity PNG");
    }
  } catch (const cv::Exception& e) {
    return makeError(ErrorCode::kIo, path.string() + ": " + e.err);
  }
  return common::Ok{};
}

common::Result<cv::Mat> readDisparityPng(const fs::path& path) {
  const cv::Mat encoded = cv::imread(path.string(), cv::IMREAD_UNCHANGED);
  if (encoded.empty()) return makeError(ErrorCode::kNotFound, path.string() + ": cannot read");
  if (encoded.type() != CV_16UC1) {
    return makeError(ErrorCode::kCorrupt, path.string() + ": not a 16-bit single-channel PNG");
  }
  cv::Mat disparity;
  encoded.convertTo(disparity, CV_32F, 1.0 / 256.0);
  disparity.setTo(-1.0f, encoded == 0);
  return disparity;
}

cv::Mat colorizeDisparity(const cv::Mat& disparity_px, double max_disparity) {
  CV_Assert(disparity_px.type() == CV_32FC1);
  const cv::Mat valid = disparity_px >= 0;
  if (max_disparity <= 0)
    cv::minMaxLoc(disparity_px, nullptr, &max_disparity, nullptr, nullptr, valid);
  cv::Mat scaled;
  disparity_px.convertTo(scaled, CV_8U, max_disparity > 0 ? 255.0 / max_disparity : 0.0);
  cv::Mat colour;
  cv::applyColorMap(scaled, colour, cv::COLORMAP_TURBO);
  colour.setTo(cv::Scalar::all(0), ~valid);
  return colour;
}

common::Status writePly(const fs::path& path, const common::PointCloud& cloud) {
  std::ofstream out(path, std::ios::binary);
  if (!out) return makeError(ErrorCode::kIo, path.string() + ": cannot write");
  out << "ply\nformat binary_little_endian 1.0\ncomment stereomap cloud\nelement vertex "
      << cloud.size() << "\nproperty float x\nproperty float y\nproperty float z\n";
  if (cloud.hasIntensity())
    out << "property uchar red\nproperty uchar green\nproperty uchar blue\n";
  out << "end_header\n";
  for (size_t i = 0; i < cloud.size(); ++i) {
    out.write(reinterpret_cast<const char*>(cloud.points[i].data()), 3 * sizeof(float));
    if (cloud.hasIntensity()) {
      const uint8_t grey[3] = {cloud.intensity[i], cloud.intensity[i], cloud.intensity[i]};
      out.write(reinterpret_cast<const char*>(grey), 3);
    }
  }
  if (!out) return makeError(ErrorCode::kIo, path.string() + ": write failed");
  return common::Ok{};
}

common::Result<MiddleburyPair> loadMiddleburyPair(const fs::path& dir) {
  MiddleburyPair pair;
  pair.name = dir.filename().string();
  pair.left = cv::imread((dir / "left.png").string(), cv::IMREAD_GRAYSCALE);
  pair.right = cv::imread((dir / "right.png").string(), cv::IMREAD_GRAYSCALE);
  const cv::Mat gt = cv::imread((dir / "disp_gt.png").string(), cv::IMREAD_UNCHANGED);
  if (pair.left.empty() || pair.right.empty() || gt.empty()) {
    return makeError(ErrorCode::kNotFound,
                     dir.string() + ": needs left.png, right.png, disp_gt.png");
  }
  double scale = 0;
  std::ifstream info(dir / "info.txt");
  for (std::string line; std::getline(info, line);) {
    if (line.rfind("scale=", 0) == 0) scale = std::stod(line.substr(6));
    if (line.rfind("max_disparity=", 0) == 0) pair.max_disparity = std::stoi(line.substr(14));
  }
  if (!(scale > 0) || pair.max_disparity <= 0) {
    return makeError(ErrorCode::kCorrupt,
                     (dir / "info.txt").string() + ": needs scale=... and max_disparity=...");
  }
  gt.convertTo(pair.ground_truth, CV_32F, 1.0 / scale);
  pair.evaluated = gt > 0;
  const cv::Mat mask = cv::imread((dir / "mask_nonocc_derived.png").string(), cv::IMREAD_GRAYSCALE);
  if (!mask.empty()) pair.evaluated &= mask > 0;
  return pair;
}

DisparityScore scoreDisparity(const cv::Mat& estimate_px, const MiddleburyPair& pair,
                              double threshold_px) {
  CV_Assert(estimate_px.type() == CV_32FC1 && estimate_px.size() == pair.ground_truth.size());
  DisparityScore score;
  size_t valid = 0, bad = 0;
  for (int v = 0; v < estimate_px.rows; ++v) {
    const float* est = estimate_px.ptr<float>(v);
    const float* gt = pair.ground_truth.ptr<float>(v);
    const uint8_t* evaluated = pair.evaluated.ptr<uint8_t>(v);
    for (int u = 0; u < estimate_px.cols; ++u) {
      if (!evaluated[u]) continue;
      ++score.evaluated;
      if (!(est[u] >= 0)) continue;
      ++valid;
      bad += std::abs(est[u] - gt[u]) > threshold_px;
    }
  }
  if (score.evaluated == 0) return score;
  score.density = static_cast<double>(valid) / static_cast<double>(score.evaluated);
  score.bad = static_cast<double>(bad) / static_cast<double>(score.evaluated);
  score.bad_among_valid = valid ? static_cast<double>(bad) / static_cast<double>(valid) : 0.0;
  return score;
}

}  // namespace stereomap::stereo
