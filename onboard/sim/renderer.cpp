#include "onboard/sim/renderer.hpp"

#include <opencv2/core/utility.hpp>

#include <random>

namespace stereomap::sim {

using common::Rigid3;
using common::Vec3;

Renderer::Renderer(const Scene& scene, camera::StereoCamera camera, RenderOptions options)
    : scene_(scene), camera_(camera), options_(options) {}

void Renderer::renderView(const Rigid3& T_map_camera, cv::Mat* image, cv::Mat* depth) const {
  if (image != nullptr) image->create(camera_.height, camera_.width, CV_8UC1);
  if (depth != nullptr) depth->create(camera_.height, camera_.width, CV_32FC1);
  const Eigen::Matrix3d R = T_map_camera.rotation.toRotationMatrix();
  const Vec3 origin = T_map_camera.translation;
  cv::parallel_for_(cv::Range(0, camera_.height), [&](const cv::Range& rows) {
    for (int v = rows.start; v < rows.end; ++v) {
      uint8_t* image_row = image != nullptr ? image->ptr<uint8_t>(v) : nullptr;
      float* depth_row = depth != nullptr ? depth->ptr<float>(v) : nullptr;
      for (int u = 0; u < camera_.width; ++u) {
        // Ray with camera-frame z = 1, so the hit's t is its depth exactly.
        const Vec3 direction = R * camera_.rayThrough(u, v);
        const auto hit = scene_.intersect(origin, direction, options_.max_depth);
        if (depth_row != nullptr) depth_row[u] = hit ? static_cast<float>(hit->t) : 0.0f;
        if (image_row != nullptr) {
          // Sky: a flat grey with no texture, so stereo finds nothing there (as outdoors).
          image_row[u] = hit ? scene_.textureAt(origin + hit->t * direction, hit->box) : 200;
        }
      }
    }
  });
  if (image != nullptr && options_.noise_sigma > 0) {
    cv::Mat noise(image->size(), CV_16SC1);
    cv::theRNG().state = options_.noise_seed;
    cv::randn(noise, 0, options_.noise_sigma);
    cv::Mat noisy;
    image->convertTo(noisy, CV_16SC1);
    noisy += noise;
    noisy.convertTo(*image, CV_8UC1);
  }
}

StereoFrame Renderer::render(const Rigid3& T_map_camera) const {
  StereoFrame frame;
  frame.T_map_camera = T_map_camera;
  renderView(T_map_camera, &frame.left, &frame.depth);
  const Rigid3 T_left_right{common::Quat::Identity(), Vec3(camera_.baseline, 0, 0)};
  renderView(T_map_camera * T_left_right, &frame.right, nullptr);
  return frame;
}

cv::Mat Renderer::renderDepth(const Rigid3& T_map_camera) const {
  cv::Mat depth;
  renderView(T_map_camera, nullptr, &depth);
  return depth;
}

}  // namespace stereomap::sim
