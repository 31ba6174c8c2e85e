#include "onboard/camera/chessboard.hpp"

#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

namespace stereomap::camera {

using common::ErrorCode;
using common::makeError;

namespace {

// Corners of the board in one image, refined to sub-pixel; empty when not found.
std::vector<cv::Point2f> findCorners(const cv::Mat& grey, cv::Size inner) {
  std::vector<cv::Point2f> corners;
  const bool found = cv::findChessboardCorners(
      grey, inner, corners, cv::CALIB_CB_ADAPTIVE_THRESH | cv::CALIB_CB_NORMALIZE_IMAGE);
  if (!found) return {};
  cv::cornerSubPix(grey, corners, cv::Size(11, 11), cv::Size(-1, -1),
                   cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 30, 0.01));
  return corners;
}

double viewRms(const std::vector<cv::Point3f>& object, const std::vector<cv::Point2f>& image,
               const cv::Mat& rvec, const cv::Mat& tvec, const cv::Matx33d& K,
               const cv::Mat& distortion) {
  std::vector<cv::Point2f> projected;
  cv::projectPoints(object, rvec, tvec, K, distortion, projected);
  double sum = 0;
  for (size_t i = 0; i < image.size(); ++i) {
    const cv::Point2f d = projected[i] - image[i];
    sum += d.dot(d);
  }
  return std::sqrt(sum / static_cast<double>(image.size()));
}

}  // namespace

size_t ChessboardReport::used_views() const {
  return static_cast<size_t>(
      std::count_if(views.begin(), views.end(), [](const auto& v) { return v.used; }));
}

common::Result<ChessboardReport> calibrateFromChessboards(
    const std::vector<std::pair<std::filesystem::path, std::filesystem::path>>& pairs,
    const ChessboardOptions& options, const ProgressCallback& progress) {
  if (options.inner_corners.width < 2 || options.inner_corners.height < 2 ||
      !(options.square_m > 0)) {
    return makeError(ErrorCode::kInvalidArgument,
                     "the board needs at least 2x2 inner corners and a positive square size");
  }
  ChessboardReport report;
  std::vector<std::vector<cv::Point2f>> left_points, right_points;
  cv::Size image_size;
  for (size_t i = 0; i < pairs.size(); ++i) {
    ChessboardView view{pairs[i].first, pairs[i].second};
    const cv::Mat left = cv::imread(view.left.string(), cv::IMREAD_GRAYSCALE);
    const cv::Mat right = cv::imread(view.right.string(), cv::IMREAD_GRAYSCALE);
    if (left.empty() || right.empty()) {
      view.reason = "cannot read " + (left.empty() ? view.left : view.right).string();
    } else if (left.size() != right.size() ||
               (image_size.area() != 0 && left.size() != image_size)) {
      view.reason = "image size differs from the first pair's";
    } else {
      image_size = left.size();
      auto l = findCorners(left, options.inner_corners);
      auto r = l.empty() ? std::vector<cv::Point2f>{} : findCorners(right, options.inner_corners);
      if (l.empty() || r.empty()) {
        view.reason =
            std::string("board not found in the ") + (l.empty() ? "left" : "right") + " image";
      } else {
        view.used = true;
        left_points.push_back(std::move(l));
        right_points.push_back(std::move(r));
      }
    }
    report.views.push_back(std::move(view));
    if (progress) progress(i + 1, pairs.size());
  }
  if (left_points.size() < 3) {
    return makeError(ErrorCode::kInvalidArgument,
                     "the board was found in only " + std::to_string(left_points.size()) + " of " +
                         std::to_string(pairs.size()) +
                         " pairs; at least 3 are needed (check --board and the images)");
  }

  std::vector<cv::Point3f> board;
  for (int y = 0; y < options.inner_corners.height; ++y) {
    for (int x = 0; x < options.inner_corners.width; ++x) {
      board.emplace_back(static_cast<float>(x * options.square_m),
                         static_cast<float>(y * options.square_m), 0.0f);
    }
  }
  const std::vector<std::vector<cv::Point3f>> objects(left_points.size(), board);

  StereoCalibration& c = report.calibration;
  c.image_size = image_size;
  cv::Mat K_left, K_right, D_left, D_right;
  std::vector<cv::Mat> rvecs_left, tvecs_left, rvecs_right, tvecs_right;
  report.rms_left_px =
      cv::calibrateCamera(objects, left_points, image_size, K_left, D_left, rvecs_left, tvecs_left);
  report.rms_right_px = cv::calibrateCamera(objects, right_points, image_size, K_right, D_right,
                                            rvecs_right, tvecs_right);
  c.left = {cv::Matx33d(K_left), D_left.reshape(1, 1)};
  c.right = {cv::Matx33d(K_right), D_right.reshape(1, 1)};

  cv::Mat R, T, E, F;
  report.rms_stereo_px = cv::stereoCalibrate(
      objects, left_points, right_points, K_left, D_left, K_right, D_right, image_size, R, T, E, F,
      cv::CALIB_FIX_INTRINSIC,
      cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 100, 1e-5));
  c.R = cv::Matx33d(R);
  c.T = cv::Vec3d(T.at<double>(0), T.at<double>(1), T.at<double>(2));

  size_t used = 0;
  for (auto& view : report.views) {
    if (!view.used) continue;
    view.rms_left_px = viewRms(board, left_points[used], rvecs_left[used], tvecs_left[used],
                               c.left.K, c.left.distortion);
    view.rms_right_px = viewRms(board, right_points[used], rvecs_right[used], tvecs_right[used],
                                c.right.K, c.right.distortion);
    ++used;
  }
  if (auto status = validateCalibration(c); !status) return status.error();
  return report;
}

}  // namespace stereomap::camera
