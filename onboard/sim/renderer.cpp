#include "onboard/sim/renderer.hpp"

#include <algorithm>
#include <cmath>
#include <functional>

#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>

#include <random>

#include "common/statistics.hpp"

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
    cv::Mat sharp;
    Renderer(scene_, fine, fine_options).renderView(T_map_camera, &sharp, nullptr);
    cv::resize(sharp, *image, cv::Size(camera_.width, camera_.height), 0, 0, cv::INTER_AREA);
    if (depth != nullptr) renderView(T_map_camera, nullptr, depth);
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
}

CameraModel CameraModel::typical() {
  return {.noise_sigma = 1.5,
          .shot_noise = 0.014,
          .blur_sigma = 0.5,
          .exposure_s = 0.004,
          .vignetting = 0.15,
          .right_gain = 1.05,
          .gamma = 1.1};
}

CameraModel CameraModel::poor() {
  return {.noise_sigma = 3.0,
          .shot_noise = 0.055,
          .blur_sigma = 1.0,
          .exposure_s = 0.010,
          .vignetting = 0.30,
          .right_gain = 1.10,
          .gamma = 1.25};
}

std::optional<CameraModel> CameraModel::preset(const std::string& name) {
  if (name == "clean") return clean();
  if (name == "typical") return typical();
  if (name == "poor") return poor();
  return std::nullopt;
}

namespace {

// A line kernel from -motion/2 to +motion/2 (pixels), summing to 1; empty when shorter than a
// tenth of a pixel.
cv::Mat motionKernel(const Eigen::Vector2d& motion) {
  const double length = motion.norm();
  if (!(length >= 0.1)) return {};
  const int half = static_cast<int>(std::ceil(0.5 * length)) + 1;
  cv::Mat kernel = cv::Mat::zeros(2 * half + 1, 2 * half + 1, CV_32F);
  // Sampled finely along the segment with bilinear weights, so that a sub-pixel length blurs
  // by that much.
  const int samples = std::max(8, static_cast<int>(std::ceil(8 * length)));
  for (int i = 0; i < samples; ++i) {
    const Eigen::Vector2d p = motion * ((i + 0.5) / samples - 0.5);
    const double x = p.x() + half, y = p.y() + half;
    const int x0 = static_cast<int>(std::floor(x)), y0 = static_cast<int>(std::floor(y));
    const double fx = x - x0, fy = y - y0;
    kernel.at<float>(y0, x0) += static_cast<float>((1 - fx) * (1 - fy));
    kernel.at<float>(y0, x0 + 1) += static_cast<float>(fx * (1 - fy));
    kernel.at<float>(y0 + 1, x0) += static_cast<float>((1 - fx) * fy);
    kernel.at<float>(y0 + 1, x0 + 1) += static_cast<float>(fx * fy);
  }
  return kernel / cv::sum(kernel)[0];
}

}  // namespace

void Renderer::finishImage(const Rigid3& T_map_camera, double gain, const cv::Mat& motion,
                           cv::Mat& image) const {
  const CameraModel& model = options_.camera;
  if (model.vignetting > 0 || gain != 1.0) {
    // Light falls off towards the corners (r^2 from the principal point, 1 at the farthest
    // corner); the camera's gain scales it all.
    cv::Mat light;
    image.convertTo(light, CV_32F);
    const double cx = camera_.cx, cy = camera_.cy;
    const double corner2 = std::max(cx * cx, (camera_.width - cx) * (camera_.width - cx)) +
                           std::max(cy * cy, (camera_.height - cy) * (camera_.height - cy));
    for (int v = 0; v < light.rows; ++v) {
      float* row = light.ptr<float>(v);
      for (int u = 0; u < light.cols; ++u) {
        const double r2 = ((u - cx) * (u - cx) + (v - cy) * (v - cy)) / corner2;
        row[u] = static_cast<float>(row[u] * gain * (1.0 - model.vignetting * r2));
      }
    }
    light.convertTo(image, CV_8U);
  }
  if (model.blur_sigma > 0) cv::GaussianBlur(image, image, cv::Size(), model.blur_sigma);
  if (!motion.empty())
    cv::filter2D(image, image, -1, motion, cv::Point(-1, -1), 0, cv::BORDER_REFLECT);
  if (model.noise_sigma > 0 || model.shot_noise > 0) {
    // A fresh pattern per image (one seed for all would be fixed-pattern noise that stereo
    // and tracking lock onto), reproducible from the seed and the pose.
    uint64_t seed = options_.noise_seed;
    for (const double v :
         {T_map_camera.translation.x(), T_map_camera.translation.y(), T_map_camera.translation.z(),
          T_map_camera.rotation.w(), T_map_camera.rotation.x(), T_map_camera.rotation.y()}) {
      seed = seed * 0x9E3779B97F4A7C15ull ^ std::hash<double>{}(v);
    }
    cv::RNG rng(seed);
    if (model.shot_noise > 0) {
      // sigma^2 = read^2 + shot * level, per pixel.
      cv::Mat level, unit(image.size(), CV_32F);
      image.convertTo(level, CV_32F);
      rng.fill(unit, cv::RNG::NORMAL, 0, 1);
      cv::Mat sigma;
      cv::sqrt(level * model.shot_noise + model.noise_sigma * model.noise_sigma, sigma);
      level += unit.mul(sigma);
      level.convertTo(image, CV_8U);
    } else {
      cv::Mat noise(image.size(), CV_16SC1);
      rng.fill(noise, cv::RNG::NORMAL, 0, model.noise_sigma);
      cv::Mat noisy;
      image.convertTo(noisy, CV_16SC1);
      noisy += noise;
      noisy.convertTo(image, CV_8UC1);
    }
  }
  if (model.gamma != 1.0) {
    cv::Mat table(1, 256, CV_8U);
    for (int i = 0; i < 256; ++i) {
      table.at<uint8_t>(i) =
          cv::saturate_cast<uint8_t>(255.0 * std::pow(i / 255.0, 1.0 / model.gamma));
    }
    cv::LUT(image, table, image);
  }
}

StereoFrame Renderer::render(const Rigid3& T_map_camera,
                             const std::optional<Exposure>& exposure) const {
  StereoFrame frame;
  frame.T_map_camera = T_map_camera;
  renderView(T_map_camera, &frame.left, &frame.depth);
  const Rigid3 T_left_right{common::Quat::Identity(), Vec3(camera_.baseline, 0, 0)};
  const Rigid3 T_map_right = T_map_camera * T_left_right;
  renderView(T_map_right, &frame.right, nullptr);
  cv::Mat motion;
  if (exposure && options_.camera.exposure_s > 0) {
    // The scene point seen at the image centre, at the median depth of the view, moves this
    // far in the image while the shutter is open (one kernel for the whole image: rotation
    // blurs alike everywhere; for translation it is right at the median depth).
    std::vector<float> depths;
    for (int v = 0; v < frame.depth.rows; ++v) {
      const float* row = frame.depth.ptr<float>(v);
      for (int u = 0; u < frame.depth.cols; ++u) {
        if (row[u] > 0) depths.push_back(row[u]);
      }
    }
    if (const auto median_depth = common::median(std::move(depths))) {
      const double z = *median_depth;
      const Vec3 p_map = T_map_camera * Vec3(0, 0, z);
      const auto open = camera_.project(exposure->T_map_camera_open.inverse() * p_map);
      const auto close = camera_.project(exposure->T_map_camera_close.inverse() * p_map);
      if (open && close) motion = motionKernel(*close - *open);
    }
  }
  finishImage(T_map_camera, 1.0, motion, frame.left);
  finishImage(T_map_right, options_.camera.right_gain, motion, frame.right);
  return frame;
}

cv::Mat Renderer::renderDepth(const Rigid3& T_map_camera) const {
  cv::Mat depth;
  renderView(T_map_camera, nullptr, &depth);
  return depth;
}

}  // namespace stereomap::sim
