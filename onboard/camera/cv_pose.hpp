// OpenCV's pose pairs (rvec, tvec: a Rodrigues vector and a translation, as solvePnP gives
// them) as our rigid transforms.
#pragma once

#include <opencv2/core.hpp>

#include "common/geometry.hpp"

namespace stereomap::camera {

common::Rigid3 rigidFromRvecTvec(const cv::Mat& rvec, const cv::Mat& tvec);

}  // namespace stereomap::camera
