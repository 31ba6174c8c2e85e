#include "onboard/posegraph/place_memory.hpp"

#include "onboard/camera/cv_pose.hpp"

#include <algorithm>
#include <opencv2/calib3d.hpp>
#include <opencv2/core/eigen.hpp>
#include <opencv2/features2d.hpp>
#include <unordered_set>

namespace stereomap::posegraph {
namespace {

using common::Rigid3;
using common::Vec3;

// Pixel of a place-frame point in the current camera after the left perturbation xi of
// T_current_place.
std::optional<Eigen::Vector2d> projectPerturbed(const camera::StereoCamera& camera,
                                                const Rigid3& T_current_place, const Vec6& xi,
                                                const Vec3& point_place) {
  Eigen::Quaterniond dq;
  Eigen::Vector3d dt;
  se3Exp(xi, dq, dt);
  const Rigid3 perturbed = Rigid3{dq, dt} * T_current_place;
  return camera.project(perturbed * point_place);
}

// ORB's keypoints sit on whole pixels of their pyramid level: a pixel of disparity is
// several centimetres of depth at 3 m. The disparity is found again by the sum of absolute
// differences of 9x9 patches along the row, within 2 px of the feature match, and refined by
// a parabola through the best and its neighbours; nullopt at the image border or when the
// best is at the end of the search.
std::optional<double> subpixelDisparity(const cv::Mat& left, const cv::Mat& right,
                                        const cv::Point2f& at, double matched_disparity) {
  constexpr int kHalf = 4, kSearch = 2;
  const int x = cvRound(at.x), y = cvRound(at.y);
  const int d0 = cvRound(matched_disparity);
  // Every pixel read: left columns x +- kHalf, right columns x - d +- kHalf for d within
  // d0 +- kSearch (d0 may be below kSearch: then right columns beyond x are read too).
  if (y - kHalf < 0 || y + kHalf >= left.rows || x - kHalf < 0 || x + kHalf >= left.cols ||
      x - d0 - kSearch - kHalf < 0 || x - d0 + kSearch + kHalf >= right.cols) {
    return std::nullopt;
  }
  double cost[2 * kSearch + 1];
  for (int k = -kSearch; k <= kSearch; ++k) {
    const int d = d0 + k;
    double sum = 0;
    for (int dy = -kHalf; dy <= kHalf; ++dy) {
      const uint8_t* l = left.ptr<uint8_t>(y + dy);
      const uint8_t* r = right.ptr<uint8_t>(y + dy);
      for (int dx = -kHalf; dx <= kHalf; ++dx) sum += std::abs(int{l[x + dx]} - int{r[x + dx - d]});
    }
    cost[k + kSearch] = sum;
  }
  int best = 0;
  for (int k = 1; k <= 2 * kSearch; ++k) {
    if (cost[k] < cost[best]) best = k;
  }
  if (best == 0 || best == 2 * kSearch) return std::nullopt;
  const double a = cost[best - 1], b = cost[best], c = cost[best + 1];
  const double curvature = a - 2 * b + c;
  const double offset = curvature > 0 ? 0.5 * (a - c) / curvature : 0.0;
  return d0 + (best - kSearch) + offset;
}

}  // namespace

PlaceMemory::PlaceMemory(const camera::StereoCamera& camera, const PlaceOptions& options)
    : camera_(camera), options_(options) {}

Place PlaceMemory::describe(int keyframe, const cv::Mat& left, const cv::Mat& right) const {
  Place place;
  place.keyframe = keyframe;
  auto orb = cv::ORB::create(options_.features);
  std::vector<cv::KeyPoint> left_points, right_points;
  cv::Mat left_descriptors, right_descriptors;
  orb->detectAndCompute(left, cv::noArray(), left_points, left_descriptors);
  orb->detectAndCompute(right, cv::noArray(), right_points, right_descriptors);
  if (left_points.empty() || right_points.empty()) return place;

  // Stereo: the best right feature on the same row (+-1 px, rectified) at a positive
  // disparity, with a clear Hamming distance.
  const double min_disparity = camera_.disparityFromDepth(options_.max_depth_m);
  for (size_t i = 0; i < left_points.size(); ++i) {
    const cv::Point2f& l = left_points[i].pt;
    int best = -1, best_distance = 256, second = 256;
    for (size_t j = 0; j < right_points.size(); ++j) {
      const cv::Point2f& r = right_points[j].pt;
      if (std::abs(r.y - l.y) > 1.0f || l.x - r.x < min_disparity || l.x - r.x > 200) continue;
      const int distance =
          static_cast<int>(cv::norm(left_descriptors.row(static_cast<int>(i)),
                                    right_descriptors.row(static_cast<int>(j)), cv::NORM_HAMMING));
      if (distance < best_distance) {
        second = best_distance;
        best_distance = distance;
        best = static_cast<int>(j);
      } else if (distance < second) {
        second = distance;
      }
    }
    if (best < 0 || best_distance > 50 || best_distance > 0.8 * second) continue;
    const auto refined = subpixelDisparity(left, right, l, l.x - right_points[best].pt.x);
    if (!refined || *refined < min_disparity) continue;
    const double disparity = *refined;
    const double z = camera_.depthFromDisparity(disparity);
    place.points.push_back(camera_.rayThrough(l.x, l.y) * z);
    place.keypoints.push_back(left_points[i]);
    place.descriptors.push_back(left_descriptors.row(static_cast<int>(i)));
  }
  return place;
}

void PlaceMemory::remember(Place place) { places_.push_back(std::move(place)); }

std::optional<PlaceMatch> PlaceMemory::recognise(const Place& current,
                                                 const std::vector<int>& candidates) const {
  if (current.descriptors.empty()) return std::nullopt;
  const std::unordered_set<int> wanted(candidates.begin(), candidates.end());
  cv::BFMatcher matcher(cv::NORM_HAMMING);
  std::optional<PlaceMatch> best;
  const cv::Matx33d K(camera_.fx, 0, camera_.cx, 0, camera_.fy, camera_.cy, 0, 0, 1);
  for (const Place& place : places_) {
    if (!wanted.count(place.keyframe) || place.descriptors.rows < options_.min_matches) continue;
    std::vector<std::vector<cv::DMatch>> knn;
    matcher.knnMatch(current.descriptors, place.descriptors, knn, 2);
    std::vector<cv::Point3d> object;
    std::vector<cv::Point2d> image;
    for (const auto& pair : knn) {
      if (pair.size() < 2 || pair[0].distance > options_.ratio * pair[1].distance) continue;
      const Vec3& p = place.points[static_cast<size_t>(pair[0].trainIdx)];
      object.emplace_back(p.x(), p.y(), p.z());
      image.push_back(current.keypoints[static_cast<size_t>(pair[0].queryIdx)].pt);
    }
    if (static_cast<int>(object.size()) < options_.min_matches) continue;
    cv::Mat rvec, tvec;
    std::vector<int> inliers;
    if (!cv::solvePnPRansac(object, image, K, cv::noArray(), rvec, tvec, false, 300,
                            static_cast<float>(options_.ransac_px), 0.999, inliers,
                            cv::SOLVEPNP_EPNP) ||
        static_cast<int>(inliers.size()) < options_.min_inliers) {
      continue;
    }
    std::vector<cv::Point3d> inlier_object;
    std::vector<cv::Point2d> inlier_image;
    for (const int i : inliers) {
      inlier_object.push_back(object[static_cast<size_t>(i)]);
      inlier_image.push_back(image[static_cast<size_t>(i)]);
    }
    cv::solvePnPRefineLM(inlier_object, inlier_image, K, cv::noArray(), rvec, tvec);
    const Rigid3 T_current_place = camera::rigidFromRvecTvec(rvec, tvec);
    if (best && static_cast<int>(inliers.size()) <= best->inliers) continue;

    // Information J^T J / sigma^2 of the reprojection error, by central differences over
    // perturbations of the transform; expressed for T_place_current (the edge's direction).
    Eigen::Matrix<double, 6, 6> JtJ = Eigen::Matrix<double, 6, 6>::Zero();
    const double h = 1e-6;
    for (size_t i = 0; i < inlier_object.size(); ++i) {
      const Vec3 p(inlier_object[i].x, inlier_object[i].y, inlier_object[i].z);
      Eigen::Matrix<double, 2, 6> J;
      bool ok = true;
      for (int d = 0; d < 6 && ok; ++d) {
        Vec6 step = Vec6::Zero();
        step[d] = h;
        const auto plus = projectPerturbed(camera_, T_current_place, step, p);
        const auto minus = projectPerturbed(camera_, T_current_place, -step, p);
        if (!plus || !minus)
          ok = false;
        else
          J.col(d) = (*plus - *minus) / (2 * h);
      }
      if (ok) JtJ += J.transpose() * J;
    }
    // The perturbation xi is on the left of T_current_place; for the edge's direction,
    // T_place_current = T_current_place^-1, it is the right perturbation -xi (the graph's
    // error is a right perturbation), which leaves J^T J as it is.
    const Rigid3 T_place_current = T_current_place.inverse();
    const Eigen::Matrix<double, 6, 6> information =
        JtJ / (options_.pixel_sigma * options_.pixel_sigma);

    PlaceMatch match;
    match.keyframe = place.keyframe;
    match.T_place_current = T_place_current;
    match.information = 0.5 * (information + information.transpose());
    match.matches = static_cast<int>(object.size());
    match.inliers = static_cast<int>(inliers.size());
    best = match;
  }
  return best;
}

}  // namespace stereomap::posegraph
