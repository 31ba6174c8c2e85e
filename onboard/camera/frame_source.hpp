// Where stereo frames come from on board: the simulator now, datasets and real cameras later.
// A source hands out rectified grey pairs in order, with a ground-truth pose when it has one.
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include <opencv2/core.hpp>

#include "common/geometry.hpp"
#include "onboard/camera/stereo_camera.hpp"

namespace stereomap::camera {

struct SourceFrame {
  uint64_t index = 0;
  int64_t stamp_ns = 0;
  cv::Mat left;                                 // CV_8UC1, rectified
  cv::Mat right;                                // CV_8UC1, rectified
  std::optional<common::Rigid3> T_map_body;     // ground truth, when the source knows it
  std::optional<common::Rigid3> T_body_camera;  // the left camera's mount on the body
  // The map frame in an outer world, when the map moves in it: a ship's deck, mapped in its own
  // frame (what stands on a moving deck stays put there), while the deck's own motion is
  // measured in the world. The vehicle's navigation in the world is T_world_map * T_map_body.
  // Unset: the map frame is the world.
  std::optional<common::Rigid3> T_world_map;
  // The mount, or a forward-looking camera at the body's origin when the source does not say.
  common::Rigid3 mount() const {
    return T_body_camera.value_or(
        common::Rigid3{common::bodyFromCameraRotation(), common::Vec3::Zero()});
  }
  // The left camera's pose in the map from the ground truth (the body at the map's origin
  // without it). The first frame's is where odometry anchors its world frame in the map.
  common::Rigid3 T_map_camera_truth() const {
    return T_map_body.value_or(common::Rigid3{}) * mount();
  }
  // The left image's noise (imageNoiseSigma, grey levels) measured before rectification, on
  // some frames of sources that rectify: interpolation hides most of it afterwards.
  std::optional<double> raw_noise_sigma;
};

class FrameSource {
 public:
  virtual ~FrameSource() = default;
  virtual const StereoCamera& camera() const = 0;
  // The next frame, or nullopt at the end of the stream.
  virtual std::optional<SourceFrame> next() = 0;
  // One line for logs, e.g. "sim (seed 1, room 12 x 10 m)".
  virtual std::string describe() const = 0;
  // Whether frames come in real time (a camera; the simulator, which stamps frames as a camera
  // would): a pipeline that falls behind skips to the newest frame instead of queueing them.
  // Recorded data sets are not live and keep every frame.
  virtual bool live() const { return false; }
  // Passes over the next `frames` frames without producing them (a live source).
  virtual void skip(uint64_t frames) {
    for (uint64_t i = 0; i < frames && next(); ++i) {
    }
  }
};

}  // namespace stereomap::camera
