// The default odometry (VoMode::kFast): see odometry.hpp.
#pragma once

#include <opencv2/core.hpp>
#include <optional>
#include <vector>

#include "onboard/odometry/detail/refine.hpp"
#include "onboard/odometry/detail/window.hpp"
#include "onboard/odometry/odometry.hpp"

namespace stereomap::odometry::detail {

class FastTracker {
 public:
  FastTracker(const camera::StereoCamera& camera, const VoOptions& options);
  // Pose of the current left camera in the world (first camera) frame.
  VoEstimate track(const cv::Mat& left, const cv::Mat& right);

 private:
  struct Keyframe {
    std::vector<common::Vec3> points;  // keyframe camera frame
    std::vector<int64_t> ids;          // landmark ids, kept while a point is carried
    // Evidence behind each point: its observations' weights (inverse depth variance, up to a
    // factor) summed, and the weighted sum of their positions; points = sum / weight.
    std::vector<double> weight;
    std::vector<common::Vec3> weighted_sum;
    common::Rigid3 T_world_keyframe;
    int64_t frame = 0;
    Eigen::Matrix<double, 6, 6> covariance = Eigen::Matrix<double, 6, 6>::Zero();
  };
  // A point carried into a new keyframe: its pixel there, and its fused position (in that
  // camera's frame) with the evidence behind it.
  struct Carried {
    cv::Point2f pixel;
    common::Vec3 point;
    double weight = 0;
    int64_t id = 0;
  };
  // One frame's image pyramids: the left, and the right levelled by the right camera's gain.
  struct Pyramids {
    std::vector<cv::Mat> left, right;
  };
  // Keyframe points followed from the previous frame into this one (their index in the
  // keyframe, their pixel now); those lost on the way are marked in alive_.
  struct Followed {
    std::vector<size_t> point;
    std::vector<cv::Point2f> pixel;
  };
  // The pose RANSAC found from the followed points, and its inliers (pixel, keyframe point).
  struct Solved {
    common::Rigid3 T_current_keyframe;
    std::vector<cv::Point2f> inlier_points;
    std::vector<size_t> inlier_point;
  };

  // track()'s steps, in order.
  Pyramids pyramids(const cv::Mat& left, const cv::Mat& right);
  VoEstimate start(Pyramids& pyramids, const cv::Mat& left);  // the first frame
  Followed follow(const std::vector<cv::Mat>& pyramid, const common::Rigid3& predicted,
                  const cv::Size& size);
  // nullopt: too few points or inliers (`features`: the points RANSAC had).
  std::optional<Solved> solve(const Followed& followed, const common::Rigid3& predicted,
                              int& features);
  // Lost: moves on as predicted and starts again from this frame.
  VoEstimate lose(Pyramids& pyramids, const cv::Mat& left, const common::Rigid3& predicted);
  // The inliers' stereo matches in this pair (as `observations`) and the pose refined on both
  // images.
  RefineResult refine(const Pyramids& pyramids, const Solved& solved,
                      const common::Rigid3& predicted, std::vector<Observation>& observations);
  // Which observations the refined pose keeps; those fuse into their points and join the
  // window with this frame.
  std::vector<bool> keepGood(const Solved& solved, const std::vector<Observation>& observations,
                             const common::Rigid3& T_current_keyframe);

  // Stereo points of the current frame: the carried ones plus new FAST corners matched in
  // the right image.
  void makeKeyframe(const std::vector<cv::Mat>& pyramid, const std::vector<cv::Mat>& right_pyramid,
                    const cv::Mat& left, const std::vector<Carried>& carried,
                    const common::Rigid3& T_world_camera,
                    const Eigen::Matrix<double, 6, 6>& covariance);
  // Adds a stereo observation (point in the keyframe's frame) to keyframe point i.
  void fuse(size_t i, const common::Vec3& point, double disparity);
  // Left-to-right KLT on rectified images: the match in the right image, its column corrected
  // by the right camera's estimated offset (as a calibrated camera would see it); x NaN where
  // no valid match.
  std::vector<cv::Point2f> matchRight(const std::vector<cv::Mat>& left_pyramid,
                                      const std::vector<cv::Mat>& right_pyramid,
                                      const std::vector<cv::Point2f>& left_points,
                                      const std::vector<float>* guess_disparity);

  // Window adjustment after the frame's own refinement: moves the current pose, the keyframe's
  // pose (while in the window) and the keyframe's points.
  void adjustWindow(common::Rigid3& T_world_current);
  // The window begins again at the current frame (start, or a lost frame).
  void restartWindow(const common::Rigid3& T_world_current);
  // The right gain's estimate moved by what the matches of this frame still see.
  void updateRightGain(const cv::Mat& left, const cv::Mat& right,
                       const std::vector<cv::Point2f>& left_points,
                       const std::vector<cv::Point2f>& right_points,
                       const std::vector<cv::Point2f>& matches);
  // A left pixel and its disparity as a point in the camera frame.
  common::Vec3 stereoPoint(double u, double v, double disparity) const {
    return camera_.rayThrough(u, v) * camera_.depthFromDisparity(disparity);
  }
  // A right-image match with its column corrected, back to the raw one the window keeps.
  std::optional<Eigen::Vector2d> rawRight(const std::optional<Eigen::Vector2d>& corrected) const {
    if (!corrected) return std::nullopt;
    return Eigen::Vector2d(corrected->x() + right_offset_, corrected->y());
  }

  camera::StereoCamera camera_;
  VoOptions options_;
  SlidingWindow window_;
  bool initialised_ = false;
  int64_t frame_ = 0;
  int64_t next_landmark_ = 0;
  // Estimated horizontal offset of the right image against its calibration (pixels, raw
  // column minus calibrated column); every disparity is corrected by it.
  double right_offset_ = 0;
  // The right camera's gain against the left, from the matched patches (matchRight, a running
  // mean): Lucas-Kanade assumes equal brightness, and a 5 % mismatch biased every stereo match
  // by over half a pixel on the sim's typical camera. The right image is levelled by it before
  // matching when it is more than kLevelledFromGain from 1 (see track()).
  double right_gain_ = 1.0;
  static constexpr double kLevelledFromGain = 0.03;
  double levelled_by_ = 1.0;  // the gain this frame's right image was levelled by
  cv::Mat levelled_right_;    // reused: a fresh image per frame costs page faults
  Keyframe keyframe_;
  std::vector<cv::Point2f> tracks_;  // each keyframe point in the previous frame
  std::vector<bool> alive_;
  std::vector<cv::Mat> previous_pyramid_;
  common::Rigid3 T_world_previous_;
  common::Rigid3 motion_;  // T_current_previous of the last step (constant velocity)
};

}  // namespace stereomap::odometry::detail
