#include "onboard/sim/renderer.hpp"

#include <functional>

#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>

#include <random>

namespace stereomap::sim {

using common::Rigid3;
using common::Vec3;

Renderer::Renderer(const Scene& scene, camera::StereoCamera camera, RenderOptions options)
    : scene_(scene), camera_(camera), options_(options) {}

namespace {

// The image rows/columns a box can cover (conservative: the whole image when any corner is
// behind the camera). Pixels outside it need no intersection test with that box.
cv::Rect projectedRect(const SceneBox& box, const Rigid3& T_camera_map,
                       const camera::StereoCamera& camera) {
  const cv::Rect image(0, 0, camera.width, camera.height);
  double u_min = 1e9, u_max = -1e9, v_min = 1e9, v_max = -1e9;
  for (int corner = 0; corner < 8; ++corner) {
    const Vec3 p_map((corner & 1) ? box.max.x() : box.min.x(),
                     (corner & 2) ? box.max.y() : box.min.y(),
                     (corner & 4) ? box.max.z() : box.min.z());
    const Vec3 p = T_camera_map * p_map;
    if (p.z() < 1e-3) return image;
    const auto uv = camera.project(p);
    u_min = std::min(u_min, uv->x());
    u_max = std::max(u_max, uv->x());
    v_min = std::min(v_min, uv->y());
    v_max = std::max(v_max, uv->y());
  }
  const cv::Rect rect(
      cv::Point(static_cast<int>(std::floor(u_min)) - 1, static_cast<int>(std::floor(v_min)) - 1),
      cv::Point(static_cast<int>(std::ceil(u_max)) + 2, static_cast<int>(std::ceil(v_max)) + 2));
  return rect & image;
}

}  // namespace

void Renderer::renderView(const Rigid3& T_map_camera, cv::Mat* image, cv::Mat* depth) const {
  if (image != nullptr && options_.supersample > 1) {
    // The image at s times the resolution (pixel centres: u' = s u + (s - 1) / 2), averaged
    // down; depth at the camera's own resolution.
    const int s = options_.supersample;
    camera::StereoCamera fine = camera_;
    fine.width *= s;
    fine.height *= s;
    fine.fx *= s;
    fine.fy *= s;
    fine.cx = s * camera_.cx + (s - 1) / 2.0;
    fine.cy = s * camera_.cy + (s - 1) / 2.0;
    RenderOptions fine_options = options_;
    fine_options.supersample = 1;
    fine_options.noise_sigma = 0;
    fine_options.blur_sigma = 0;
    cv::Mat sharp;
    Renderer(scene_, fine, fine_options).renderView(T_map_camera, &sharp, nullptr);
    cv::resize(sharp, *image, cv::Size(camera_.width, camera_.height), 0, 0, cv::INTER_AREA);
    if (depth != nullptr) renderView(T_map_camera, nullptr, depth);
    finishImage(T_map_camera, *image);
    return;
  }
  if (image != nullptr) image->create(camera_.height, camera_.width, CV_8UC1);
  if (depth != nullptr) depth->create(camera_.height, camera_.width, CV_32FC1);
  const Eigen::Matrix3d R = T_map_camera.rotation.toRotationMatrix();
  const Vec3 origin = T_map_camera.translation;
  const Rigid3 T_camera_map = T_map_camera.inverse();
  std::vector<cv::Rect> rects;
  for (const auto& box : scene_.boxes()) rects.push_back(projectedRect(box, T_camera_map, camera_));

  cv::parallel_for_(cv::Range(0, camera_.height), [&](const cv::Range& rows) {
    std::vector<int> row_boxes;
    for (int v = rows.start; v < rows.end; ++v) {
      row_boxes.clear();
      for (size_t i = 0; i < rects.size(); ++i) {
        if (v >= rects[i].y && v < rects[i].y + rects[i].height) row_boxes.push_back(int(i));
      }
      uint8_t* image_row = image != nullptr ? image->ptr<uint8_t>(v) : nullptr;
      float* depth_row = depth != nullptr ? depth->ptr<float>(v) : nullptr;
      for (int u = 0; u < camera_.width; ++u) {
        // Ray with camera-frame z = 1, so the hit's t is its depth exactly.
        const Vec3 direction = R * camera_.rayThrough(u, v);
        const Vec3 inverse = direction.cwiseInverse();
        std::optional<RayHit> hit;
        double best_t = options_.max_depth;
        for (int i : row_boxes) {
          if (u < rects[i].x || u >= rects[i].x + rects[i].width) continue;
          const double t = scene_.entryDistance(i, origin, inverse);
          if (t > 0 && t <= best_t) {
            best_t = t;
            hit = RayHit{t, i};
          }
        }
        if (depth_row != nullptr) depth_row[u] = hit ? static_cast<float>(hit->t) : 0.0f;
        if (image_row != nullptr) {
          // Sky: a flat grey with no texture, so stereo finds nothing there (as outdoors).
          image_row[u] = hit ? scene_.textureAt(origin + hit->t * direction, hit->box) : 200;
        }
      }
    }
  });
  if (image != nullptr) finishImage(T_map_camera, *image);
}

void Renderer::finishImage(const Rigid3& T_map_camera, cv::Mat& image) const {
  if (options_.blur_sigma > 0) cv::GaussianBlur(image, image, cv::Size(), options_.blur_sigma);
  if (options_.noise_sigma > 0) {
    // A fresh pattern per image (one seed for all would be fixed-pattern noise that stereo
    // and tracking lock onto), reproducible from the seed and the pose.
    uint64_t seed = options_.noise_seed;
    for (const double v :
         {T_map_camera.translation.x(), T_map_camera.translation.y(), T_map_camera.translation.z(),
          T_map_camera.rotation.w(), T_map_camera.rotation.x(), T_map_camera.rotation.y()}) {
      seed = seed * 0x9E3779B97F4A7C15ull ^ std::hash<double>{}(v);
    }
    cv::Mat noise(image.size(), CV_16SC1);
    cv::RNG rng(seed);
    rng.fill(noise, cv::RNG::NORMAL, 0, options_.noise_sigma);
    cv::Mat noisy;
    image.convertTo(noisy, CV_16SC1);
    noisy += noise;
    noisy.convertTo(image, CV_8UC1);
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
