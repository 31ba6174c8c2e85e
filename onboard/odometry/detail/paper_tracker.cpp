#include "onboard/odometry/detail/paper_tracker.hpp"

#include <ceres/ceres.h>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <numeric>

#include "onboard/odometry/detail/refine.hpp"

namespace stereomap::odometry::detail {

namespace {

using common::Rigid3;
using common::Vec3;

// R from the paper's Euler angles (eq. 6): R = Rz(yaw) Ry(pitch) Rx(roll) in camera axes.
template <typename T>
void eulerToMatrix(const T* e, T R[9]) {
  const T cy = cos(e[0]), sy = sin(e[0]), cp = cos(e[1]), sp = sin(e[1]), cr = cos(e[2]),
          sr = sin(e[2]);
  R[0] = cy * cp;
  R[1] = cy * sp * sr - sy * cr;
  R[2] = cy * sp * cr + sy * sr;
  R[3] = sy * cp;
  R[4] = sy * sp * sr + cy * cr;
  R[5] = sy * sp * cr - cy * sr;
  R[6] = -sp;
  R[7] = cp * sr;
  R[8] = cp * cr;
}

// Eq. (5): P_c - (R P_p + t) for one point pair.
struct PointToPoint {
  PointToPoint(const Vec3& c, const Vec3& p) : c(c), p(p) {}
  template <typename T>
  bool operator()(const T* euler, const T* t, T* r) const {
    T R[9];
    eulerToMatrix(euler, R);
    for (int i = 0; i < 3; ++i) {
      r[i] = T(c[i]) -
             (R[3 * i] * T(p.x()) + R[3 * i + 1] * T(p.y()) + R[3 * i + 2] * T(p.z()) + t[i]);
    }
    return true;
  }
  Vec3 c, p;
};

// LM from R = I, t = 0 on the given pairs (the paper's 1e-6 / 1e-8 tolerances).
Rigid3 fitMotion(const std::vector<Vec3>& current, const std::vector<Vec3>& previous,
                 const std::vector<size_t>& use, double tolerance) {
  double euler[3] = {0, 0, 0}, t[3] = {0, 0, 0};
  ceres::Problem problem;
  for (size_t i : use) {
    problem.AddResidualBlock(new ceres::AutoDiffCostFunction<PointToPoint, 3, 3, 3>(
                                 new PointToPoint(current[i], previous[i])),
                             nullptr, euler, t);
  }
  ceres::Solver::Options options;
  options.linear_solver_type = ceres::DENSE_QR;
  options.function_tolerance = tolerance;
  options.max_num_iterations = 50;
  options.logging_type = ceres::SILENT;
  ceres::Solver::Summary summary;
  ceres::Solve(options, &problem, &summary);
  double R[9];
  eulerToMatrix(euler, R);
  Eigen::Matrix3d M;
  M << R[0], R[1], R[2], R[3], R[4], R[5], R[6], R[7], R[8];
  return Rigid3{common::Quat(M).normalized(), Vec3(t[0], t[1], t[2])};
}

Vec3 triangulate(const camera::StereoCamera& c, cv::Point2f l, cv::Point2f r) {
  const double d = std::max(static_cast<double>(l.x - r.x), 1e-3);  // eq. (3)
  const double z = c.baseline * c.fx / d;
  return {c.baseline * (l.x - c.cx) / d, c.baseline * c.fx * (l.y - c.cy) / (c.fy * d), z};
}

}  // namespace

std::vector<cv::Point2f> harrisCorners(const cv::Mat& image, double k, int nms_window, int count) {
  cv::Mat response, dilated;
  cv::cornerHarris(image, response, 3, 3, k);
  cv::dilate(response, dilated,
             cv::getStructuringElement(cv::MORPH_RECT, {nms_window, nms_window}));
  std::vector<std::pair<float, cv::Point2f>> peaks;
  for (int y = 0; y < response.rows; ++y) {
    const float* r = response.ptr<float>(y);
    const float* d = dilated.ptr<float>(y);
    for (int x = 0; x < response.cols; ++x) {
      if (r[x] > 0 && r[x] >= d[x])
        peaks.emplace_back(r[x], cv::Point2f(static_cast<float>(x), static_cast<float>(y)));
    }
  }
  const size_t keep = std::min(peaks.size(), static_cast<size_t>(count));
  std::partial_sort(peaks.begin(), peaks.begin() + static_cast<long>(keep), peaks.end(),
                    [](const auto& a, const auto& b) { return a.first > b.first; });
  std::vector<cv::Point2f> corners;
  for (size_t i = 0; i < keep; ++i) corners.push_back(peaks[i].second);
  return corners;
}

double ncc(const cv::Mat& a, cv::Point2f pa, const cv::Mat& b, cv::Point2f pb, int window) {
  const int h = window / 2;
  const cv::Rect ra(static_cast<int>(pa.x) - h, static_cast<int>(pa.y) - h, window, window);
  const cv::Rect rb(static_cast<int>(pb.x) - h, static_cast<int>(pb.y) - h, window, window);
  const cv::Rect ia(0, 0, a.cols, a.rows), ib(0, 0, b.cols, b.rows);
  if ((ra & ia) != ra || (rb & ib) != rb) return -1;
  double sa = 0, sb = 0, saa = 0, sbb = 0, sab = 0;
  for (int y = 0; y < window; ++y) {
    const uchar* pa_row = a.ptr<uchar>(ra.y + y) + ra.x;
    const uchar* pb_row = b.ptr<uchar>(rb.y + y) + rb.x;
    for (int x = 0; x < window; ++x) {
      const double va = pa_row[x], vb = pb_row[x];
      sa += va;
      sb += vb;
      saa += va * va;
      sbb += vb * vb;
      sab += va * vb;
    }
  }
  const double n = window * window;
  const double cov = sab - sa * sb / n, var_a = saa - sa * sa / n, var_b = sbb - sb * sb / n;
  return var_a > 0 && var_b > 0 ? cov / std::sqrt(var_a * var_b) : -1;
}

PaperTracker::PaperTracker(const camera::StereoCamera& camera, const VoOptions& options)
    : camera_(camera), options_(options) {}

PaperTracker::StereoFrame PaperTracker::stereoFrame(const cv::Mat& left,
                                                    const cv::Mat& right) const {
  StereoFrame frame{left.clone(), right.clone(), {}, {}};  // kept for the next frame
  const auto lc =
      harrisCorners(left, options_.harris_k, options_.nms_window, options_.paper_corners);
  const auto rc =
      harrisCorners(right, options_.harris_k, options_.nms_window, options_.paper_corners);
  const double max_disparity = camera_.width / 3.0;
  for (const auto& l : lc) {
    double best = options_.ncc_min;
    int pick = -1;
    for (size_t j = 0; j < rc.size(); ++j) {  // along the same row (rectified), d > 0
      const double d = l.x - rc[j].x;
      if (std::abs(rc[j].y - l.y) > 1 || d <= 0 || d > max_disparity) continue;
      const double score = ncc(left, l, right, rc[j], options_.ncc_window);
      if (score > best) {
        best = score;
        pick = static_cast<int>(j);
      }
    }
    if (pick < 0) continue;
    frame.corners.push_back(l);
    frame.right_corners.push_back(rc[static_cast<size_t>(pick)]);
  }
  return frame;
}

VoEstimate PaperTracker::track(const cv::Mat& left, const cv::Mat& right) {
  VoEstimate estimate;
  StereoFrame current = stereoFrame(left, right);
  estimate.features = static_cast<int>(current.corners.size());
  if (!initialised_) {
    initialised_ = !current.corners.empty();
    previous_ = std::move(current);
    estimate.state = initialised_ ? TrackingState::kOk : TrackingState::kLost;
    estimate.T_world_camera = T_world_camera_;
    return estimate;
  }
  // Circular matching: current left -> previous left -> previous right (its stereo partner)
  // -> current right -> current left must close: each step is the best NCC within the
  // search radius, taken both ways between frames.
  const double radius = camera_.width / 8.0;
  const auto best = [&](const cv::Mat& a, cv::Point2f p, const cv::Mat& b,
                        const std::vector<cv::Point2f>& candidates) {
    double top = options_.ncc_min;
    int pick = -1;
    for (size_t j = 0; j < candidates.size(); ++j) {
      if (cv::norm(candidates[j] - p) > radius) continue;
      const double score = ncc(a, p, b, candidates[j], options_.ncc_window);
      if (score > top) {
        top = score;
        pick = static_cast<int>(j);
      }
    }
    return pick;
  };
  std::vector<Vec3> now, before;
  std::vector<cv::Point2f> pixels;
  for (size_t i = 0; i < current.corners.size(); ++i) {
    const int j = best(left, current.corners[i], previous_.left, previous_.corners);
    if (j < 0) continue;
    const size_t pj = static_cast<size_t>(j);
    if (best(previous_.left, previous_.corners[pj], left, current.corners) != static_cast<int>(i) ||
        best(right, current.right_corners[i], previous_.right, previous_.right_corners) != j ||
        best(previous_.right, previous_.right_corners[pj], right, current.right_corners) !=
            static_cast<int>(i)) {
      continue;
    }
    now.push_back(triangulate(camera_, current.corners[i], current.right_corners[i]));
    before.push_back(triangulate(camera_, previous_.corners[pj], previous_.right_corners[pj]));
    pixels.push_back(current.corners[i]);
  }
  estimate.features = static_cast<int>(now.size());
  Rigid3 T_current_previous;
  std::vector<size_t> best_inliers;
  if (now.size() >= 3) {
    // RANSAC: 3 random pairs, LM, inliers within 2 px in the current left image.
    std::vector<size_t> all(now.size());
    std::iota(all.begin(), all.end(), 0);
    for (int iteration = 0; iteration < options_.paper_ransac_iterations; ++iteration) {
      std::vector<size_t> sample;
      std::sample(all.begin(), all.end(), std::back_inserter(sample), 3, random_);
      const Rigid3 T = fitMotion(now, before, sample, 1e-6);
      std::vector<size_t> inliers;
      for (size_t i : all) {
        const auto pixel = project(camera_, T * before[i]);
        if (pixel && (*pixel - Eigen::Vector2d(pixels[i].x, pixels[i].y)).norm() <=
                         options_.paper_ransac_px) {
          inliers.push_back(i);
        }
      }
      if (inliers.size() > best_inliers.size()) best_inliers = std::move(inliers);
    }
    if (best_inliers.size() >= 3) T_current_previous = fitMotion(now, before, best_inliers, 1e-8);
  }
  estimate.inliers = static_cast<int>(best_inliers.size());
  // Not in the paper: a motion from fewer inliers than degraded_inliers is not trusted (the
  // frame is lost and the pose kept), as in the fast mode.
  estimate.state = estimate.inliers >= options_.ok_inliers         ? TrackingState::kOk
                   : estimate.inliers >= options_.degraded_inliers ? TrackingState::kDegraded
                                                                   : TrackingState::kLost;
  // Eqs. (7)-(9): chain the inverse frame-to-frame motions (identity when lost).
  if (estimate.state != TrackingState::kLost)
    T_world_camera_ = T_world_camera_ * T_current_previous.inverse();
  estimate.T_world_camera = T_world_camera_;
  estimate.keyframe = true;
  previous_ = std::move(current);
  return estimate;
}

}  // namespace stereomap::odometry::detail
