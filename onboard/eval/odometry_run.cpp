#include "onboard/eval/odometry_run.hpp"

#include <optional>

#include "common/statistics.hpp"

namespace stereomap::eval {

double OdometryRun::medianMilliseconds() const {
  return common::median(milliseconds).value_or(0.0);
}

namespace {

// Both runs: the odometry over every frame; with a graph, every frame followed by it.
OdometryRun run(camera::FrameSource& source, const odometry::VoOptions& options,
                posegraph::GraphFollower* graph) {
  odometry::StereoOdometry vo(source.camera(), options);
  OdometryRun run;
  std::optional<common::Rigid3> anchor;
  while (auto frame = source.next()) {
    const auto e = vo.track(frame->left, frame->right);
    run.milliseconds.push_back(e.milliseconds);
    run.lost += e.state == odometry::TrackingState::kLost;
    run.degraded += e.state == odometry::TrackingState::kDegraded;
    run.keyframes += e.keyframe;
    run.right_offset_px = e.right_offset_px;
    run.right_gain = e.right_gain;

    const common::Rigid3 truth = frame->T_map_camera_truth();
    if (!anchor) anchor = truth;
    const double t = static_cast<double>(frame->stamp_ns) * 1e-9;
    run.truth.push_back({t, truth});
    run.estimate.push_back({t, *anchor * e.T_world_camera});
    if (graph) {
      graph->follow({frame->stamp_ns, e.T_world_camera, e.covariance, e.keyframe,
                     e.state == odometry::TrackingState::kLost, frame->left, frame->right});
    }
  }
  if (graph) {
    const auto poses = graph->finish();
    for (size_t i = 0; i < poses.size(); ++i) {
      run.optimised.push_back({run.estimate[i].t, *anchor * poses[i]});
    }
    const auto stats = graph->stats();
    run.loops = stats.loops;
    run.tracks = stats.tracks;
    run.joined_tracks = stats.joined_tracks;
    run.solve_ms_max = stats.solve_ms_max;
  }
  return run;
}

}  // namespace

OdometryRun runOdometry(camera::FrameSource& source, const odometry::VoOptions& options) {
  return run(source, options, nullptr);
}

OdometryRun runOdometryWithGraph(camera::FrameSource& source, const odometry::VoOptions& options,
                                 const posegraph::KeyframeGraphOptions& graph_options) {
  // In the caller's thread: the same result as a vehicle's background graph, reproducibly.
  posegraph::GraphFollower graph(source.camera(), graph_options, /*background=*/false);
  return run(source, options, &graph);
}

}  // namespace stereomap::eval
