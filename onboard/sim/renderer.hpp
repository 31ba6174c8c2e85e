// Renders exact rectified stereo pairs of a Scene: left and right grey images, plus the
// left camera's true depth (z, metres; 0 where the ray hits nothing). Uses both cores.
#pragma once

#include <optional>
#include <string>

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

// What a real stereo rig does to the exact images; every field at its default leaves them
// exact. Applied in the order light meets them: vignetting and the right camera's gain, lens
// defocus and motion blur, the sensor's noise (shot and read), the response curve (gamma),
// 8 bits. Presets by name: clean, typical, poor (preset()).
struct CameraModel {
  // Read noise: Gaussian, grey levels, the same at every level. Drawn afresh for every image,
  // as a sensor's, reproducibly from RenderOptions::noise_seed and the camera's pose.
  double noise_sigma = 0.0;
  // Shot (photon) noise: the variance grows by this much per grey level of the pixel.
  double shot_noise = 0.0;
  double blur_sigma = 0.0;  // defocus: Gaussian blur, pixels
  // Motion blur: the shutter is open this long, centred on the frame's pose; the image is
  // smeared along the motion of the image centre's scene point (at the median depth) over
  // that time. Needs the poses at the exposure's start and end (Renderer::render).
  double exposure_s = 0.0;
  double vignetting = 0.0;  // light lost in the image's corners (fraction), falling as r^2
  double right_gain = 1.0;  // the right camera's gain over the left's (exposure mismatch)
  double gamma = 1.0;       // response curve: out = 255 (in / 255)^(1 / gamma)

  // clean: exact images. typical (a good rig in daylight): noise sigma 2 at mid grey (read
  // 1.5, shot 0.014), 5 % gain mismatch, defocus 0.5 px, 4 ms exposure, 15 % vignetting,
  // gamma 1.1. poor (a cheap rig, dim light): sigma 4 at mid grey (read 3, shot 0.055),
  // 10 % mismatch, defocus 1 px, 10 ms, 30 % vignetting, gamma 1.25.
  static CameraModel clean() { return {}; }
  static CameraModel typical();
  static CameraModel poor();
  // The preset of that name, or nullopt.
  static std::optional<CameraModel> preset(const std::string& name);
};

struct RenderOptions {
  double max_depth = 40.0;  // metres; farther surfaces are not rendered
  CameraModel camera;
  uint32_t noise_seed = 1;
  // Anti-aliasing, as a real lens and sensor put a sharp painted edge between pixels (which
  // sub-pixel corners rely on). Above 1: the mean of s x s rays (s = supersample) in each pixel
  // that an edge crosses (where the box hit or the paint changes), one ray elsewhere, and the
  // texture's detail finer than the pixel faded to its mean. 1: one ray per pixel centre and
  // the exact texture (the rooms' images).
  int supersample = 1;
  // With supersample above 1: the first pass (one ray a pixel) four neighbouring pixels at a
  // time in floats, within a float's rounding of the reference in doubles (false), whose deck
  // frames take about twice as long (83.7-86.1 against 43.4-44.8 ms in alternating runs).
  bool lanes = true;
};

class Renderer {
 public:
  Renderer(const Scene& scene, camera::StereoCamera camera, RenderOptions options = {});
  // `exposure`: the left camera's poses when the shutter opens and closes (motion blur, with
  // CameraModel::exposure_s > 0); without it the images have none.
  struct Exposure {
    common::Rigid3 T_map_camera_open, T_map_camera_close;
  };
  StereoFrame render(const common::Rigid3& T_map_camera,
                     const std::optional<Exposure>& exposure = std::nullopt) const;
  // Only the left camera's true depth (CV_32FC1), e.g. for ground-truth coverage.
  cv::Mat renderDepth(const common::Rigid3& T_map_camera) const;
  const camera::StereoCamera& camera() const { return camera_; }

 private:
  // Renders one camera: the exact grey image and (if depth != nullptr) its depth.
  void renderView(const common::Rigid3& T_map_camera, cv::Mat* image, cv::Mat* depth) const;
  // The camera model on an exact image: `gain` for this camera, `motion` the blur's kernel
  // (empty: none); noise drawn afresh for this pose.
  void finishImage(const common::Rigid3& T_map_camera, double gain, const cv::Mat& motion,
                   cv::Mat& image) const;

  const Scene& scene_;
  camera::StereoCamera camera_;
  RenderOptions options_;
};

}  // namespace stereomap::sim
