// Visual odometry on real and simulated stereo (issue 4): KITTI 01 frames 0-50, the EuRoC
// clip where the vehicle stands still, and a sim flight with turns, height changes, image
// noise and blur. Figures are reported in docs/BENCHMARKS.md.
#include "onboard/odometry/odometry.hpp"

#include <gtest/gtest.h>

#include <algorithm>

#include "onboard/camera/dataset_source.hpp"
#include "onboard/eval/metrics.hpp"
#include "onboard/sim/sim_source.hpp"
#include "tests/support/data.hpp"

namespace stereomap::odometry {
namespace {

struct VoRun {
  common::Trajectory gt, est;  // left camera poses; the estimate anchored at the first GT pose
  std::vector<double> ms;
  int lost = 0;
  double medianMs() const {
    auto sorted = ms;
    std::sort(sorted.begin(), sorted.end());
    return sorted.empty() ? 0 : sorted[sorted.size() / 2];
  }
};

VoRun runOn(camera::FrameSource& source, const VoOptions& options) {
  StereoOdometry vo(source.camera(), options);
  VoRun run;
  std::optional<common::Rigid3> anchor;
  while (auto frame = source.next()) {
    const auto e = vo.track(frame->left, frame->right, frame->stamp_ns);
    run.ms.push_back(e.milliseconds);
    run.lost += e.state == TrackingState::kLost;
    const double t = static_cast<double>(frame->stamp_ns) * 1e-9;
    const common::Rigid3 gt = *frame->T_map_body * frame->T_body_camera.value_or(common::Rigid3{});
    if (!anchor) anchor = gt;
    run.gt.push_back({t, gt});
    run.est.push_back({t, *anchor * e.T_world_camera});
  }
  return run;
}

void report(const char* what, const VoRun& run, const std::vector<double>& lengths) {
  const auto drift = eval::kittiDrift(run.gt, run.est, lengths);
  const auto sim3 = eval::absoluteError(run.gt, run.est, eval::Alignment::kSim3);
  const auto se3 = eval::absoluteError(run.gt, run.est, eval::Alignment::kSe3);
  std::printf("%s: %zu frames, %d lost, median %.1f ms; ATE Sim3 %.3f m (scale %.3f), SE3 %.3f m, "
              "path %.1f m; rotation ATE %.3f deg\n",
              what, run.est.size(), run.lost, run.medianMs(), sim3.translation.rmse,
              sim3.alignment.scale, se3.translation.rmse, eval::pathLength(run.gt),
              se3.rotation.rmse);
  for (const auto& d : drift) {
    std::printf("  %5.0f m: %3zu segments, %.2f %%, %.2f deg/100 m\n", d.length_m, d.segments,
                d.translation_percent, d.rotation_deg_per_100m);
  }
}

const auto kKitti = testing::kDataDir / "kitti_stereo_seq2";

TEST(Odometry, KittiExcerpt) {
  STEREOMAP_SKIP_WITHOUT(kKitti);
  for (const auto mode : {VoMode::kFast, VoMode::kPaper}) {
    auto source = camera::openDatasetSource("kitti:" + kKitti.string(), {});
    ASSERT_TRUE(source.ok()) << source.error().message;
    const VoRun run = runOn(**source, {.mode = mode});
    report(mode == VoMode::kFast ? "KITTI fast" : "KITTI paper", run, {10, 20});
  }
}

TEST(Odometry, SimFlight) {
  for (const auto mode : {VoMode::kFast, VoMode::kPaper}) {
    sim::SimSourceOptions options{.seed = 1, .rate_hz = 10.0, .max_frames = 150};
    options.render.noise_sigma = 2.0;
    sim::SimSource source(options);
    const VoRun run = runOn(source, {.mode = mode});
    report(mode == VoMode::kFast ? "sim fast" : "sim paper", run, {2, 5});
  }
}

}  // namespace
}  // namespace stereomap::odometry
