// Renders exact rectified stereo pairs of a Scene: left and right grey images, plus the
// left camera's true depth (z, metres; 0 where the ray hits nothing). Uses both cores.
#pragma once

#include <opencv2/core.hpp>

#include "common/geometry.hpp"
#include "onboard/camera/stereo_camera.hpp"
#include "onboard/sim/scene.hpp"

namespace stereomap::sim {

struct StereoFrame {
  cv::Mat left;                 // CV_8UC1
  cv::Mat right;                // CV_8UC1
  cv::Mat depth;                // CV_32FC1, left camera z in metres, 0 = no surface
  common::Rigid3 T_map_camera;  // left camera
};

struct RenderOptions {
  double max_depth = 40.0;  // metres; farther surfaces are not rendered
  // Gaussian image noise, grey levels (0 = exact images): drawn afresh for every image, as a
  // sensor's, reproducibly from the seed and the camera's pose.
  double noise_sigma = 0.0;
  uint32_t noise_seed = 1;
  double blur_sigma = 0.0;  // Gaussian blur (defocus, motion), pixels; 0 = sharp
  // Rays per pixel along each axis, averaged (anti-aliasing: a sharp painted edge then lands
  // between pixels as a real lens and sensor put it, which sub-pixel corners rely on).
  int supersample = 1;
};

class Renderer {
 public:
  Renderer(const Scene& scene, camera::StereoCamera camera, RenderOptions options = {});
  StereoFrame render(const common::Rigid3& T_map_camera) const;
  // Only the left camera's true depth (CV_32FC1), e.g. for ground-truth coverage.
  cv::Mat renderDepth(const common::Rigid3& T_map_camera) const;
  const camera::StereoCamera& camera() const { return camera_; }

 private:
  // Renders one camera: grey image and (if depth != nullptr) its depth.
  void renderView(const common::Rigid3& T_map_camera, cv::Mat* image, cv::Mat* depth) const;
  // Blur, then noise drawn afresh for this pose.
  void finishImage(const common::Rigid3& T_map_camera, cv::Mat& image) const;

  const Scene& scene_;
  camera::StereoCamera camera_;
  RenderOptions options_;
};

}  // namespace stereomap::sim
