#include "onboard/camera/rectifier.hpp"

#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>

namespace stereomap::camera {

using common::ErrorCode;
using common::makeError;

common::Result<Rectifier> Rectifier::create(const StereoCalibration& calibration,
                                            cv::Size image_size) {
  if (auto status = validateCalibration(calibration); !status) return status.error();
  Rectifier r;
  r.calibration_ = calibration;
  if (image_size.area() == 0) image_size = calibration.image_size;
  if (image_size.area() == 0) {
    return makeError(ErrorCode::kInvalidArgument, calibration.source +
                                                      ": the image size is unknown (pass it or add "
                                                      "image_width/image_height)");
  }
  r.calibration_.image_size = image_size;
  r.camera_.width = image_size.width;
  r.camera_.height = image_size.height;
  if (calibration.isRectified()) {
    r.pass_through_ = true;
    r.camera_.fx = calibration.left.K(0, 0);
    r.camera_.fy = calibration.left.K(1, 1);
    r.camera_.cx = calibration.left.K(0, 2);
    r.camera_.cy = calibration.left.K(1, 2);
    r.camera_.baseline = calibration.baseline();
    r.P_left_ =
        cv::Matx34d(r.camera_.fx, 0, r.camera_.cx, 0, 0, r.camera_.fy, r.camera_.cy, 0, 0, 0, 1, 0);
    r.P_right_ = r.P_left_;
    r.P_right_(0, 3) = -r.camera_.fx * r.camera_.baseline;
    return r;
  }
  cv::Mat R1, R2, P1, P2, Q;
  cv::stereoRectify(calibration.left.K, calibration.left.distortion, calibration.right.K,
                    calibration.right.distortion, image_size, calibration.R, calibration.T, R1, R2,
                    P1, P2, Q, cv::CALIB_ZERO_DISPARITY, 0.0, image_size);
  if (std::abs(P2.at<double>(1, 3)) > 1e-6 * std::abs(P2.at<double>(0, 3))) {
    return makeError(ErrorCode::kInvalidArgument,
                     calibration.source +
                         ": the cameras are stacked vertically; stereomap "
                         "needs a horizontal pair (right camera along +x)");
  }
  r.R_left_ = cv::Matx33d(R1);
  r.R_right_ = cv::Matx33d(R2);
  r.P_left_ = cv::Matx34d(P1);
  r.P_right_ = cv::Matx34d(P2);
  r.camera_.fx = P1.at<double>(0, 0);
  r.camera_.fy = P1.at<double>(1, 1);
  r.camera_.cx = P1.at<double>(0, 2);
  r.camera_.cy = P1.at<double>(1, 2);
  r.camera_.baseline = -P2.at<double>(0, 3) / P2.at<double>(0, 0);
  if (!(r.camera_.baseline > 0)) {
    return makeError(ErrorCode::kInvalidArgument,
                     calibration.source +
                         ": after rectification the right camera is not on "
                         "the left camera's +x side (swap left and right?)");
  }
  // Fixed-point maps: remap is about twice as fast with CV_16SC2 than with float maps.
  cv::initUndistortRectifyMap(calibration.left.K, calibration.left.distortion, R1, P1, image_size,
                              CV_16SC2, r.left_map1_, r.left_map2_);
  cv::initUndistortRectifyMap(calibration.right.K, calibration.right.distortion, R2, P2, image_size,
                              CV_16SC2, r.right_map1_, r.right_map2_);
  return r;
}

common::Status Rectifier::rectify(const cv::Mat& left, const cv::Mat& right, cv::Mat& left_out,
                                  cv::Mat& right_out) const {
  const cv::Size expected = calibration_.image_size;
  for (const auto& [name, image] : {std::pair{"left", &left}, std::pair{"right", &right}}) {
    if (image->empty())
      return makeError(ErrorCode::kInvalidArgument, std::string(name) + " image is empty");
    if (image->size() != expected) {
      return makeError(ErrorCode::kInvalidArgument,
                       std::string(name) + " image is " + std::to_string(image->cols) + "x" +
                           std::to_string(image->rows) + ", the calibration is for " +
                           std::to_string(expected.width) + "x" + std::to_string(expected.height));
    }
  }
  auto grey = [](const cv::Mat& image) {
    if (image.type() == CV_8UC1) return image;
    cv::Mat out;
    if (image.channels() == 3) {
      cv::cvtColor(image, out, cv::COLOR_BGR2GRAY);
    } else if (image.channels() == 4) {
      cv::cvtColor(image, out, cv::COLOR_BGRA2GRAY);
    } else {
      out = image;
    }
    if (out.depth() != CV_8U) out.convertTo(out, CV_8U, out.depth() == CV_16U ? 1.0 / 256 : 1.0);
    return out;
  };
  const cv::Mat left_grey = grey(left), right_grey = grey(right);
  if (pass_through_) {
    left_out = left_grey;
    right_out = right_grey;
    return common::Ok{};
  }
  cv::remap(left_grey, left_out, left_map1_, left_map2_, cv::INTER_LINEAR);
  cv::remap(right_grey, right_out, right_map1_, right_map2_, cv::INTER_LINEAR);
  return common::Ok{};
}

std::vector<cv::Point2f> Rectifier::rectifyPoints(const std::vector<cv::Point2f>& raw,
                                                  const CameraIntrinsics& camera,
                                                  const cv::Matx33d& R,
                                                  const cv::Matx34d& P) const {
  if (raw.empty()) return {};
  std::vector<cv::Point2f> out;
  cv::undistortPoints(raw, out, camera.K, camera.distortion, R, P);
  return out;
}

std::vector<cv::Point2f> Rectifier::rectifyLeftPoints(const std::vector<cv::Point2f>& raw) const {
  return rectifyPoints(raw, calibration_.left, R_left_, P_left_);
}

std::vector<cv::Point2f> Rectifier::rectifyRightPoints(const std::vector<cv::Point2f>& raw) const {
  return rectifyPoints(raw, calibration_.right, R_right_, P_right_);
}

}  // namespace stereomap::camera
