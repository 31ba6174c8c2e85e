// Disparity and cloud files for people and tools: 16-bit PNG disparity (value = disparity
// x 256, 0 = invalid: the KITTI stereo convention), a colourised picture, PLY clouds, and
// Middlebury evaluation pairs with their scores (bad-pixel rate, density).
#pragma once

#include <filesystem>
#include <string>

#include <opencv2/core.hpp>

#include "common/point_cloud.hpp"
#include "common/result.hpp"

namespace stereomap::stereo {

// `disparity_px`: CV_32F, negative or non-finite = invalid. Values are clamped to 255.99.
common::Status writeDisparityPng(const std::filesystem::path& path, const cv::Mat& disparity_px);
// Back to CV_32F pixels; invalid pixels become -1.
common::Result<cv::Mat> readDisparityPng(const std::filesystem::path& path);
// A colour picture (near = warm), invalid pixels black; max_disparity <= 0: the largest value.
cv::Mat colorizeDisparity(const cv::Mat& disparity_px, double max_disparity = 0);
// Binary little-endian PLY with x y z (and grey r g b when the cloud has intensity).
common::Status writePly(const std::filesystem::path& path, const common::PointCloud& cloud);

struct MiddleburyPair {
  std::string name;
  cv::Mat left, right;   // CV_8UC1
  cv::Mat ground_truth;  // CV_32F pixels, 0 = unknown
  cv::Mat evaluated;     // CV_8U mask: GT known and (when the folder has one) not occluded
  int max_disparity = 0;
};

// A folder with left.png, right.png, disp_gt.png, info.txt (scale, max_disparity) and
// optionally mask_nonocc_derived.png (see ../shared/data/middlebury/README.md).
common::Result<MiddleburyPair> loadMiddleburyPair(const std::filesystem::path& dir);

struct DisparityScore {
  size_t evaluated = 0;
  double density = 0;          // share of evaluated pixels with an estimate
  double bad = 0;              // share of evaluated pixels with an estimate off by > threshold
  double bad_among_valid = 0;  // bad / density
};

DisparityScore scoreDisparity(const cv::Mat& estimate_px, const MiddleburyPair& pair,
                              double threshold_px = 1.0);

}  // namespace stereomap::stereo
