#include "onboard/eval/odometry_run.hpp"

#include <algorithm>
#include <optional>

namespace stereomap::eval {

double OdometryRun::medianMilliseconds() const {
  if (milliseconds.empty()) return 0;
  auto sorted = milliseconds;
  std::nth_element(sorted.begin(), sorted.begin() + static_cast<long>(sorted.size() / 2),
                   sorted.end());
  return sorted[sorted.size() / 2];
}

namespace {

// Frames the odometry lost have no measurement of their own: between the tracked frames on
// either side, the graph's trajectory is interpolated in time (position linearly, attitude
// by slerp); at either end the nearest tracked frame's pose is kept.
void fillLostFrames(common::Trajectory& trajectory, const std::vector<bool>& lost) {
  size_t i = 0;
  while (i < trajectory.size()) {
    if (!lost[i]) {
      ++i;
      continue;
    }
    size_t end = i;
    while (end < trajectory.size() && lost[end]) ++end;
    if (i > 0 && end < trajectory.size()) {
      const auto& a = trajectory[i - 1];
      const auto& b = trajectory[end];
      for (size_t k = i; k < end; ++k) {
        const double s = (trajectory[k].t - a.t) / (b.t - a.t);
        trajectory[k].pose.translation = (1 - s) * a.pose.translation + s * b.pose.translation;
        trajectory[k].pose.rotation = a.pose.rotation.slerp(s, b.pose.rotation);
      }
    }
    i = end;
  }
}

// Both runs: the odometry over every frame; with a graph, its keyframes into it.
OdometryRun run(camera::FrameSource& source, const odometry::VoOptions& options,
                posegraph::KeyframeGraph* graph) {
  odometry::StereoOdometry vo(source.camera(), options);
  OdometryRun run;
  std::optional<common::Rigid3> anchor;
  std::vector<std::pair<int, common::Rigid3>> through_keyframe;  // per frame
  int keyframe = -1;
  bool lost_since_keyframe = false;
  std::vector<bool> was_lost;
  while (auto frame = source.next()) {
    const auto e = vo.track(frame->left, frame->right, frame->stamp_ns);
    run.milliseconds.push_back(e.milliseconds);
    run.lost += e.state == odometry::TrackingState::kLost;
    run.degraded += e.state == odometry::TrackingState::kDegraded;
    run.keyframes += e.keyframe;
    run.right_offset_px = e.right_offset_px;
    const common::Rigid3 truth = frame->T_map_body.value_or(common::Rigid3{}) *
                                 frame->T_body_camera.value_or(common::Rigid3{});
    if (!anchor) anchor = truth;
    const double t = static_cast<double>(frame->stamp_ns) * 1e-9;
    run.truth.push_back({t, truth});
    run.estimate.push_back({t, *anchor * e.T_world_camera});
    if (!graph) continue;
    const bool lost = e.state == odometry::TrackingState::kLost;
    lost_since_keyframe |= lost;
    was_lost.push_back(lost);
    // A keyframe of the odometry, or the first tracked frame after a loss (a new track).
    if ((e.keyframe || keyframe < 0 || lost_since_keyframe) && !lost) {
      const auto added = graph->add(frame->stamp_ns, e.T_world_camera, e.covariance, frame->left,
                                    frame->right, lost_since_keyframe && keyframe >= 0);
      keyframe = added.keyframe;
      lost_since_keyframe = false;
      run.solve_ms_max = std::max(run.solve_ms_max, added.solve.milliseconds);
    }
    through_keyframe.emplace_back(keyframe, e.T_world_camera);
  }
  if (graph) {
    run.loops = graph->loops();
    run.tracks = graph->tracks();
    run.joined_tracks = graph->joinedTracks();
    for (size_t i = 0; i < through_keyframe.size(); ++i) {
      const auto& [k, pose] = through_keyframe[i];
      run.optimised.push_back(
          {run.estimate[i].t, *anchor * (k < 0 ? pose : graph->correct(k, pose))});
    }
    fillLostFrames(run.optimised, was_lost);
  }
  return run;
}

}  // namespace

OdometryRun runOdometry(camera::FrameSource& source, const odometry::VoOptions& options) {
  return run(source, options, nullptr);
}

OdometryRun runOdometryWithGraph(camera::FrameSource& source, const odometry::VoOptions& options,
                                 const posegraph::KeyframeGraphOptions& graph_options) {
  posegraph::KeyframeGraph graph(source.camera(), graph_options);
  return run(source, options, &graph);
}

}  // namespace stereomap::eval
