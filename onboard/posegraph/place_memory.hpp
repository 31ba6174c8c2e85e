// Places the vehicle has seen, to find them again: each keyframe keeps ORB features of its
// left image with their 3D positions (matched along the rectified right image's rows). A new
// keyframe is compared with remembered ones near its estimated position (appearance: ORB
// matches that pass the ratio test), and a candidate is accepted only when PnP with RANSAC
// puts enough of its 3D points onto the new image (geometry). The result is the relative
// pose of the two keyframes with an information matrix from the reprojection error:
// a loop closure, or the join of a track that broke (relocalisation).
#pragma once

#include <opencv2/core.hpp>
#include <optional>
#include <vector>

#include "common/geometry.hpp"
#include "onboard/camera/stereo_camera.hpp"
#include "onboard/posegraph/se3.hpp"

namespace stereomap::posegraph {

struct PlaceOptions {
  int features = 800;
  double ratio = 0.8;    // Lowe's ratio test
  int min_matches = 40;  // appearance
  int min_inliers = 30;  // geometry
  double ransac_px = 2.0;
  double pixel_sigma = 0.7;   // reprojection noise behind the information matrix
  double max_depth_m = 12.0;  // farther stereo points are too uncertain to keep
};

struct Place {
  int keyframe = -1;                    // the caller's id
  std::vector<cv::KeyPoint> keypoints;  // left image
  cv::Mat descriptors;                  // rows: ORB descriptors of `points`
  std::vector<common::Vec3> points;     // camera frame, metres
};

struct PlaceMatch {
  int keyframe = -1;               // the remembered place
  common::Rigid3 T_place_current;  // the new keyframe's camera in the place's camera frame
  Mat6 information = Mat6::Identity();
  int matches = 0, inliers = 0;
};

class PlaceMemory {
 public:
  PlaceMemory(const camera::StereoCamera& camera, const PlaceOptions& options = {});

  // Features and stereo points of a rectified pair (CV_8UC1), not yet remembered.
  Place describe(int keyframe, const cv::Mat& left, const cv::Mat& right) const;
  void remember(Place place);
  // The best verified match of `current` among the remembered places whose keyframe is in
  // `candidates` (the caller picks them by position and age).
  std::optional<PlaceMatch> recognise(const Place& current,
                                      const std::vector<int>& candidates) const;
  size_t size() const { return places_.size(); }

 private:
  camera::StereoCamera camera_;
  PlaceOptions options_;
  std::vector<Place> places_;
};

}  // namespace stereomap::posegraph
