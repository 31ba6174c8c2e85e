#include "onboard/odometry/detail/window.hpp"

#include <cassert>

#include "onboard/odometry/detail/bundle.hpp"

namespace stereomap::odometry::detail {

void SlidingWindow::clear() {
  frames_.clear();
  landmarks_.clear();
  adjusted_.clear();
}

void SlidingWindow::addFrame(int64_t frame, const common::Rigid3& T_world_camera) {
  frames_.push_back({frame, T_world_camera, {}});
  if (frames_.size() <= size_) return;
  frames_.pop_front();
  // Forget landmarks no frame in the window sees any more.
  std::unordered_map<int64_t, common::Vec3> kept;
  for (const auto& f : frames_) {
    for (const auto& o : f.observations) kept.emplace(o.landmark, landmarks_.at(o.landmark));
  }
  landmarks_ = std::move(kept);
}

void SlidingWindow::observe(const WindowObservation& observation, const common::Vec3& world) {
  assert(!frames_.empty());
  frames_.back().observations.push_back(observation);
  landmarks_.emplace(observation.landmark, world);
}

bool SlidingWindow::adjust(int iterations, double huber_px, double& right_offset,
                           double right_offset_sigma) {
  adjusted_.clear();
  if (frames_.size() < 2) return false;
  // Landmarks seen by at least two frames constrain the poses; the rest only themselves.
  std::unordered_map<int64_t, int> seen;
  for (const auto& f : frames_) {
    for (const auto& o : f.observations) ++seen[o.landmark];
  }
  BundleProblem problem;
  problem.right_offset = right_offset;
  problem.right_offset_sigma = right_offset_sigma;
  std::unordered_map<int64_t, int> index;  // landmark id -> point
  std::vector<int64_t> ids;
  for (size_t i = 0; i < frames_.size(); ++i) {
    problem.T_camera_world.push_back(frames_[i].T_world_camera.inverse());
    for (const auto& o : frames_[i].observations) {
      if (seen[o.landmark] < 2) continue;
      const auto [it, fresh] = index.emplace(o.landmark, static_cast<int>(ids.size()));
      if (fresh) {
        ids.push_back(o.landmark);
        problem.points.push_back(landmarks_.at(o.landmark));
      }
      const int frame = static_cast<int>(i);
      problem.observations.push_back({frame, it->second, o.left.x(), o.left.y(), false});
      if (o.right)
        problem.observations.push_back({frame, it->second, o.right->x(), o.right->y(), true});
    }
  }
  if (ids.empty()) return false;
  adjustBundle(camera_, problem, {.iterations = iterations, .huber_px = huber_px});
  for (size_t i = 1; i < frames_.size(); ++i) {
    frames_[i].T_world_camera = problem.T_camera_world[i].inverse();
  }
  for (size_t j = 0; j < ids.size(); ++j) {
    landmarks_[ids[j]] = problem.points[j];
    adjusted_.insert(ids[j]);
  }
  right_offset = problem.right_offset;
  return true;
}

std::optional<common::Rigid3> SlidingWindow::pose(int64_t frame) const {
  for (const auto& f : frames_) {
    if (f.frame == frame) return f.T_world_camera;
  }
  return std::nullopt;
}

std::optional<common::Vec3> SlidingWindow::adjustedLandmark(int64_t id) const {
  if (!adjusted_.contains(id)) return std::nullopt;
  return landmarks_.at(id);
}

}  // namespace stereomap::odometry::detail
