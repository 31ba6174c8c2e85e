#include "onboard/posegraph/graph_follower.hpp"

#include <spdlog/spdlog.h>

#include <utility>

namespace stereomap::posegraph {

using common::Rigid3;

GraphFollower::GraphFollower(const camera::StereoCamera& camera,
                             const KeyframeGraphOptions& options, bool background)
    : graph_(camera, options),
      background_(background),
      min_change_m_(options.report_min_change_m),
      min_change_rad_(options.report_min_change_rad) {
  if (background_) worker_ = std::thread([this] { work(); });
}

GraphFollower::~GraphFollower() {
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
  }
  changed_.notify_all();
  if (worker_.joinable()) worker_.join();
}

void GraphFollower::process(const Pending& pending) {
  const auto added =
      graph_.add(pending.frame.stamp_ns, pending.frame.T_world_camera, pending.frame.covariance,
                 pending.frame.left, pending.frame.right, pending.new_track);
  const Rigid3 correction =
      graph_.optimised(added.keyframe) * graph_.odometry(added.keyframe).inverse();
  // Only a place moves keyframes the odometry has already left: between places the graph is
  // a chain that its solve leaves as the odometry made it.
  std::vector<KeyframePose> moved;
  if (added.place) {
    moved.reserve(static_cast<size_t>(added.keyframe) + 1);
    for (int k = 0; k <= added.keyframe; ++k) {
      moved.push_back({graph_.stamp(k), graph_.optimised(k)});
    }
  }
  std::lock_guard lock(mutex_);
  if (!moved.empty() && movedEnough(moved)) {
    new_poses_ = std::move(moved);
    reported_ = new_poses_;
  }
  processed_ = added.keyframe + 1;
  correction_ = correction;
  solve_ms_max_ = std::max(solve_ms_max_, added.solve.milliseconds);
  changed_.notify_all();
}

void GraphFollower::work() {
  for (;;) {
    Pending pending;
    {
      std::unique_lock lock(mutex_);
      changed_.wait(lock, [this] { return stopping_ || !queue_.empty(); });
      if (queue_.empty()) return;  // stopping, nothing left
      pending = std::move(queue_.front());
      queue_.pop_front();
    }
    process(pending);
  }
}

Rigid3 GraphFollower::follow(const FollowedFrame& frame) {
  lost_since_keyframe_ |= frame.lost;
  const bool enters = !frame.lost && (frame.keyframe || submitted_ == 0 || lost_since_keyframe_);
  if (enters) {
    Pending pending{submitted_, frame, lost_since_keyframe_ && submitted_ > 0};
    pending.frame.left = frame.left.clone();  // the caller's buffers move on
    pending.frame.right = frame.right.clone();
    ++submitted_;
    lost_since_keyframe_ = false;
    if (background_) {
      std::lock_guard lock(mutex_);
      queue_.push_back(std::move(pending));
      if (queue_.size() == 16) {
        spdlog::warn("pose graph: 16 keyframes wait for place recognition (it falls behind)");
      }
      changed_.notify_all();
    } else {
      process(pending);
    }
  }
  through_.push_back(submitted_ - 1);
  odometry_.push_back(frame.T_world_camera);
  lost_.push_back(frame.lost);
  stamps_.push_back(frame.stamp_ns);

  std::lock_guard lock(mutex_);
  return correction_ * frame.T_world_camera;
}

// Whether some keyframe moved by more than the thresholds since the poses last reported (a
// keyframe reported never is measured against the odometry's pose of it corrected as the
// vehicle now publishes, about what it was sent with): every correction makes the server
// fuse the session again, so that small ones wait until they add up. Under mutex_.
bool GraphFollower::movedEnough(const std::vector<KeyframePose>& moved) const {
  for (size_t k = 0; k < moved.size(); ++k) {
    const Rigid3 before = k < reported_.size() ? reported_[k].T_world_camera
                                               : correction_ * graph_.odometry(static_cast<int>(k));
    const Rigid3 change = before.inverse() * moved[k].T_world_camera;
    if (change.translation.norm() > min_change_m_ ||
        Eigen::AngleAxisd(change.rotation).angle() > min_change_rad_) {
      return true;
    }
  }
  return false;
}

std::vector<KeyframePose> GraphFollower::takeCorrection() {
  std::lock_guard lock(mutex_);
  return std::exchange(new_poses_, {});
}

void GraphFollower::waitUntilCaughtUp() {
  std::unique_lock lock(mutex_);
  changed_.wait(lock, [this] { return processed_ == submitted_; });
}

std::vector<Rigid3> GraphFollower::finish() {
  waitUntilCaughtUp();
  std::vector<Rigid3> poses(odometry_.size());
  for (size_t i = 0; i < poses.size(); ++i) {
    poses[i] = through_[i] < 0 ? odometry_[i] : graph_.correct(through_[i], odometry_[i]);
  }
  // Lost frames: interpolated in time between the tracked frames on either side (position
  // linearly, attitude by slerp); at either end the odometry's guess stays.
  for (size_t i = 0; i < poses.size();) {
    if (!lost_[i]) {
      ++i;
      continue;
    }
    size_t end = i;
    while (end < poses.size() && lost_[end]) ++end;
    if (i > 0 && end < poses.size()) {
      const double t0 = static_cast<double>(stamps_[i - 1]);
      const double t1 = static_cast<double>(stamps_[end]);
      for (size_t k = i; k < end; ++k) {
        const double s = (static_cast<double>(stamps_[k]) - t0) / (t1 - t0);
        poses[k] = common::interpolate(poses[i - 1], poses[end], s);
      }
    }
    i = end;
  }
  return poses;
}

FollowerStats GraphFollower::stats() const {
  FollowerStats stats;
  stats.keyframes = graph_.size();
  stats.loops = graph_.loops();
  stats.tracks = graph_.tracks();
  stats.joined_tracks = graph_.joinedTracks();
  std::lock_guard lock(mutex_);
  stats.solve_ms_max = solve_ms_max_;
  return stats;
}

}  // namespace stereomap::posegraph
