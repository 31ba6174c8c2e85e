#include "onboard/posegraph/keyframe_graph.hpp"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>

namespace stereomap::posegraph {
namespace {

using common::Rigid3;

// The relative pose's covariance from two accumulated world-frame covariances: what the
// later keyframe added, in its own frame (the graph's error is a right perturbation), with
// floors so that a tiny or inconsistent difference never makes an edge rigid.
Mat6 relativeInformation(const Mat6& earlier, const Mat6& later, const Rigid3& T_world_later,
                         const KeyframeGraphOptions& options) {
  Mat6 added = later - earlier;
  const Eigen::Matrix3d R = T_world_later.rotation.toRotationMatrix().transpose();
  Mat6 rotate = Mat6::Zero();
  rotate.topLeftCorner<3, 3>() = R;
  rotate.bottomRightCorner<3, 3>() = R;
  added = rotate * added * rotate.transpose();
  added = 0.5 * (added + added.transpose());
  const Eigen::SelfAdjointEigenSolver<Mat6> eigen(added);
  Vec6 values = eigen.eigenvalues();
  const double floor = std::min(options.min_sigma_rad, options.min_sigma_m);
  for (int i = 0; i < 6; ++i) values[i] = std::max(values[i], floor * floor);
  Mat6 covariance = eigen.eigenvectors() * values.asDiagonal() * eigen.eigenvectors().transpose();
  for (int i = 0; i < 3; ++i) {
    covariance(i, i) = std::max(covariance(i, i), options.min_sigma_rad * options.min_sigma_rad);
    covariance(i + 3, i + 3) =
        std::max(covariance(i + 3, i + 3), options.min_sigma_m * options.min_sigma_m);
  }
  return covariance.inverse();
}

}  // namespace

KeyframeGraph::KeyframeGraph(const camera::StereoCamera& camera,
                             const KeyframeGraphOptions& options)
    : options_(options), places_(camera, options.places) {}

int KeyframeGraph::size() const {
  std::lock_guard lock(mutex_);
  return graph_.size();
}

int KeyframeGraph::loops() const {
  std::lock_guard lock(mutex_);
  return loops_;
}

int KeyframeGraph::tracks() const {
  std::lock_guard lock(mutex_);
  return static_cast<int>(joined_.size());
}

int KeyframeGraph::joinedTracks() const {
  std::lock_guard lock(mutex_);
  return joined_.empty() ? 0
                         : static_cast<int>(std::count(joined_.begin() + 1, joined_.end(), true));
}

Rigid3 KeyframeGraph::optimised(int keyframe) const {
  std::lock_guard lock(mutex_);
  return graph_.pose(keyframe);
}

Rigid3 KeyframeGraph::odometry(int keyframe) const {
  std::lock_guard lock(mutex_);
  return odometry_.at(static_cast<size_t>(keyframe));
}

int64_t KeyframeGraph::stamp(int keyframe) const {
  std::lock_guard lock(mutex_);
  return stamps_.at(static_cast<size_t>(keyframe));
}

Rigid3 KeyframeGraph::correct(int keyframe, const Rigid3& T_world_camera) const {
  std::lock_guard lock(mutex_);
  return graph_.pose(keyframe) * odometry_.at(static_cast<size_t>(keyframe)).inverse() *
         T_world_camera;
}

G2oGraph KeyframeGraph::toG2o() const {
  std::lock_guard lock(mutex_);
  return posegraph::toG2o(graph_);
}

std::vector<int> KeyframeGraph::candidates(int current) const {
  // By the current estimates: places near where the new keyframe is thought to be, allowing
  // for the drift of the path flown since.
  const Rigid3& here = graph_.pose(current);
  const int track = track_[static_cast<size_t>(current)];
  const bool joined = joined_[static_cast<size_t>(track)];
  std::vector<std::pair<double, int>> near;
  for (int k = 0; k < current; ++k) {
    const bool same_track = track_[static_cast<size_t>(k)] == track;
    if (same_track && k + options_.recent_keyframes >= current) continue;
    const double distance = (graph_.pose(k).translation - here.translation).norm();
    double allowance =
        options_.search_radius_m + options_.drift_allowance * (path_m_[current] - path_m_[k]);
    if (!joined && !same_track) allowance += options_.new_track_sigma_m;
    if (distance <= allowance) near.emplace_back(distance, k);
  }
  std::sort(near.begin(), near.end());
  std::vector<int> out;
  for (size_t i = 0; i < near.size() && static_cast<int>(i) < options_.max_candidates; ++i) {
    out.push_back(near[i].second);
  }
  return out;
}

KeyframeAdded KeyframeGraph::add(int64_t stamp_ns, const Rigid3& T_world_camera,
                                 const Mat6& covariance, const cv::Mat& left, const cv::Mat& right,
                                 bool new_track) {
  Place place;
  KeyframeAdded added;
  std::vector<int> nearby;
  {
    std::lock_guard lock(mutex_);
    const int id = graph_.size();
    // The new vertex starts where the corrected odometry puts it.
    const Rigid3 start = id == 0
                             ? T_world_camera
                             : graph_.pose(id - 1) * odometry_.back().inverse() * T_world_camera;
    graph_.addVertex(start);
    if (id > 0) {
      const Rigid3 relative = odometry_.back().inverse() * T_world_camera;
      Mat6 information;
      if (new_track) {
        information = Mat6::Zero();
        information.diagonal() << Vec6::Constant(1.0).head<3>() /
                                      std::pow(options_.new_track_sigma_rad, 2),
            Vec6::Constant(1.0).tail<3>() / std::pow(options_.new_track_sigma_m, 2);
      } else {
        information = relativeInformation(covariance_.back(), covariance, T_world_camera, options_);
      }
      (void)graph_.addEdge(
          {id - 1, id, relative, information, new_track ? EdgeKind::kJoin : EdgeKind::kOdometry});
      path_m_.push_back(path_m_.back() + relative.translation.norm());
    } else {
      path_m_.push_back(0.0);
    }
    odometry_.push_back(T_world_camera);
    stamps_.push_back(stamp_ns);
    covariance_.push_back(covariance);
    if (id == 0 || new_track) {
      track_.push_back(static_cast<int>(joined_.size()));
      joined_.push_back(id == 0);  // the first track is the reference
    } else {
      track_.push_back(track_.back());
    }
    added.keyframe = id;
    nearby = candidates(id);
  }

  // Features and matching without the lock: the expensive part.
  place = places_.describe(added.keyframe, left, right);
  const auto match = places_.recognise(place, nearby);
  places_.remember(std::move(place));
  if (!match) return added;

  std::lock_guard lock(mutex_);
  (void)graph_.addEdge({match->keyframe, added.keyframe, match->T_place_current, match->information,
                        EdgeKind::kLoop});
  ++loops_;
  const int this_track = track_[static_cast<size_t>(added.keyframe)];
  if (track_[static_cast<size_t>(match->keyframe)] != this_track)
    joined_[static_cast<size_t>(this_track)] = true;
  added.place = match;
  added.solve = graph_.optimise();
  return added;
}

}  // namespace stereomap::posegraph
