// Visual odometry on real and simulated stereo (issue 4): KITTI 01 frames 0-50, the EuRoC
// clip where the vehicle stands still, and sim flights with turns, height changes, image
// noise and blur. Thresholds sit near the measurements in docs/BENCHMARKS.md (bench:
// stereomap-bench-vo); where they are looser than the bars, the comment says so.
#include "onboard/odometry/odometry.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <functional>

#include "onboard/camera/dataset_source.hpp"
#include "onboard/eval/metrics.hpp"
#include "onboard/eval/odometry_run.hpp"
#include "onboard/sim/sim_source.hpp"
#include "testing/data.hpp"
#include "testing/sim_flights.hpp"

namespace stereomap::odometry {
namespace {

const auto kKitti = testing::kDataDir / "kitti_stereo_seq2";
const auto kEuroc = testing::kDataDir / "euroc_v101_micro";

eval::OdometryRun onDataset(
    const std::function<common::Result<std::unique_ptr<camera::FrameSource>>(
        const std::filesystem::path&, const camera::DatasetOptions&)>& open,
    const std::filesystem::path& dir, VoMode mode) {
  auto source = open(dir, {});
  EXPECT_TRUE(source.ok()) << source.error().message;
  return source.ok() ? eval::runOdometry(**source, {.mode = mode}) : eval::OdometryRun{};
}

TEST(Odometry, KittiExcerptRotationAndShape) {
  STEREOMAP_SKIP_WITHOUT(kKitti);
  const auto run = onDataset(camera::openKitti, kKitti, VoMode::kFast);
  ASSERT_EQ(run.estimate.size(), 51u);
  EXPECT_EQ(run.lost, 0);
  const auto drift = eval::kittiDrift(run.truth, run.estimate, {20});
  const auto ate = eval::absoluteError(run.truth, run.estimate, eval::Alignment::kSim3);
  std::printf("KITTI fast: rotation %.2f deg/100 m (20 m), Sim3 ATE %.3f m, right gain %.3f\n",
              drift.at(0).rotation_deg_per_100m, ate.translation.rmse, run.right_gain);
  // Measured 2.62 deg/100 m and 0.055 m. The issue asks <= 2.0 deg/100 m and <= 0.20 m; the
  // rotation bar sits below what this excerpt's images and ground truth allow (a rotation-only
  // estimate from 1000+ tracks per frame gets 2.51: docs/BENCHMARKS.md).
  EXPECT_LE(drift.at(0).rotation_deg_per_100m, 2.7);
  EXPECT_LE(ate.translation.rmse, 0.08);
}

TEST(Odometry, EurocStandingStillDoesNotDrift) {
  STEREOMAP_SKIP_WITHOUT(kEuroc);
  const auto run = onDataset(camera::openEuroc, kEuroc, VoMode::kFast);
  ASSERT_GT(run.estimate.size(), 30u);
  const double moved = eval::largestDisplacement(run.estimate);
  std::printf("EuRoC static: largest estimated motion %.4f m\n", moved);
  EXPECT_LE(moved, 0.005);  // the issue: <= 2 cm over the clip; measured 1.0 mm
}

class SimFlight : public ::testing::TestWithParam<uint32_t> {};

TEST_P(SimFlight, WithNoiseAndBlurStaysOnTrack) {
  sim::SimSource source(testing::noisyFlight(GetParam()));
  const auto run = eval::runOdometry(source, {});
  const auto ate = eval::absoluteError(run.truth, run.estimate, eval::Alignment::kSe3);
  const double path = eval::pathLength(run.truth);
  std::printf(
      "sim room %u: path %.1f m, ATE %.4f m (%.2f%%), attitude %.3f deg, %d lost, %.1f ms\n",
      GetParam(), path, ate.translation.rmse, 100 * ate.translation.rmse / path, ate.rotation.rmse,
      run.lost, run.medianMilliseconds());
  EXPECT_EQ(run.lost, 0);
  EXPECT_LE(ate.translation.rmse, 0.005 * path);  // the issue: ATE <= 0.5% of the path
  EXPECT_LE(ate.rotation.rmse, 0.3);              // the issue: <= 0.5 deg; measured 0.14-0.19
  // A well calibrated rig: the estimated offset of the right image stays near 0 (measured
  // within 0.19 px over the flight, 0.02-0.05 at its end).
  EXPECT_LE(std::abs(run.right_offset_px), 0.15);
}

INSTANTIATE_TEST_SUITE_P(Rooms, SimFlight, ::testing::Values(1u, 2u, 3u));

// The typical and poor cameras' right image is 5 and 10 % brighter than the left (with
// vignetting, gamma, blur and shot noise). Before the odometry levelled the right image by its
// estimated gain, Lucas-Kanade's stereo matches were biased by it: room 1, 200 frames, offset
// +0.626 / +1.180 px, ATE 0.98 / 1.96 % of the path, attitude 1.13 / 3.85 deg (typical /
// poor). Measured with it: gain 1.0447 / 1.0780 (the true gains through the cameras' gamma:
// 1.0454 / 1.0792), offset +0.044 / +0.071 px, ATE 0.11 / 0.28 %, attitude 0.165 / 0.289 deg.
class GainMismatch : public ::testing::TestWithParam<std::string> {};

TEST_P(GainMismatch, IsEstimatedAndLevelledOut) {
  sim::SimSourceOptions options{.seed = 1, .rate_hz = 10.0, .max_frames = 200};
  options.render.camera = *sim::CameraModel::preset(GetParam());
  sim::SimSource source(options);
  const auto run = eval::runOdometry(source, {});
  const auto ate = eval::absoluteError(run.truth, run.estimate, eval::Alignment::kSe3);
  const double path = eval::pathLength(run.truth);
  std::printf(
      "%s camera: right gain %.4f (true %.2f), offset %+.3f px, ATE %.4f m (%.2f%%), attitude "
      "%.3f deg, %d lost\n",
      GetParam().c_str(), run.right_gain, options.render.camera.right_gain, run.right_offset_px,
      ate.translation.rmse, 100 * ate.translation.rmse / path, ate.rotation.rmse, run.lost);
  const auto& model = options.render.camera;
  EXPECT_NEAR(run.right_gain, std::pow(model.right_gain, 1.0 / model.gamma), 0.005);
  EXPECT_LE(std::abs(run.right_offset_px), 0.15);
  EXPECT_LE(ate.translation.rmse, 0.005 * path);  // the bar for sim flights
  EXPECT_LE(ate.rotation.rmse, 0.4);
}

INSTANTIATE_TEST_SUITE_P(Cameras, GainMismatch, ::testing::Values("typical", "poor"));

// A sim source whose right images sit `shift` whole pixels to the right (negative: left) of
// their calibration.
class ShiftedRight : public camera::FrameSource {
 public:
  ShiftedRight(camera::FrameSource& inner, int shift) : inner_(inner), shift_(shift) {}
  const camera::StereoCamera& camera() const override { return inner_.camera(); }
  std::string describe() const override { return inner_.describe() + ", right image shifted"; }
  std::optional<camera::SourceFrame> next() override {
    auto frame = inner_.next();
    if (!frame) return frame;
    cv::Mat shifted(frame->right.size(), frame->right.type(), cv::Scalar(0));
    const int w = frame->right.cols - std::abs(shift_), h = frame->right.rows;
    frame->right(cv::Rect(std::max(-shift_, 0), 0, w, h))
        .copyTo(shifted(cv::Rect(std::max(shift_, 0), 0, w, h)));
    frame->right = shifted;
    return frame;
  }

 private:
  camera::FrameSource& inner_;
  int shift_;
};

class MiscalibratedRig : public ::testing::TestWithParam<int> {};

TEST_P(MiscalibratedRig, RightImageOffsetIsEstimatedAndCorrected) {
  sim::SimSource sim(testing::noisyFlight(1));
  ShiftedRight source(sim, GetParam());
  const auto run = eval::runOdometry(source, {});
  const auto ate = eval::absoluteError(run.truth, run.estimate, eval::Alignment::kSe3);
  const double path = eval::pathLength(run.truth);
  std::printf("right image %+d px off: estimated %.3f px, ATE %.4f m (%.2f%%), attitude %.3f deg\n",
              GetParam(), run.right_offset_px, ate.translation.rmse,
              100 * ate.translation.rmse / path, ate.rotation.rmse);
  // Measured: within 0.1 px of the shift after 100 frames. Without the estimate (shift +1) the
  // ATE was 0.78 % of the path and the attitude 1.5 deg; with it 0.11 % and 0.20-0.47 deg
  // (rooms 1-3, shifts +-1; the first 100 frames fly on a biased depth).
  EXPECT_NEAR(run.right_offset_px, GetParam(), 0.15);
  EXPECT_LE(ate.translation.rmse, 0.005 * path);  // the bars for a sim flight
  EXPECT_LE(ate.rotation.rmse, 0.5);
}

INSTANTIATE_TEST_SUITE_P(Shifts, MiscalibratedRig, ::testing::Values(1, -1));

TEST(Odometry, PaperAttitudeFollowsEquation12) {
  // R = Rz(yaw) Ry(pitch) Rx(roll) in the paper's convention reads back its angles.
  const double yaw = 0.3, pitch = -0.2, roll = 0.1;
  const Eigen::Matrix3d R = (Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()) *
                             Eigen::AngleAxisd(pitch, Eigen::Vector3d::UnitY()) *
                             Eigen::AngleAxisd(roll, Eigen::Vector3d::UnitX()))
                                .toRotationMatrix();
  const auto e = paperAttitude(R);
  EXPECT_NEAR(e.pitch, std::asin(-R(2, 1)), 1e-12);
  EXPECT_NEAR(e.yaw, std::atan(R(2, 0) / R(2, 2)), 1e-12);
  EXPECT_NEAR(e.roll, std::atan(R(0, 1) / R(1, 1)), 1e-12);
}

TEST(Odometry, TheSamePairTwiceIsNoMotionInBothModes) {
  sim::SimSource source({.seed = 1, .rate_hz = 10.0, .max_frames = 1});
  const auto frame = source.next();
  ASSERT_TRUE(frame.has_value());
  for (const auto mode : {VoMode::kFast, VoMode::kPaper}) {
    StereoOdometry vo(source.camera(), {.mode = mode});
    vo.track(frame->left, frame->right);
    const auto e = vo.track(frame->left, frame->right);
    EXPECT_NE(e.state, TrackingState::kLost);
    EXPECT_LT(e.T_world_camera.translation.norm(), 1e-3);
    EXPECT_LT(e.T_world_camera.rotation.angularDistance(common::Quat::Identity()), 1e-3);
  }
}

}  // namespace
}  // namespace stereomap::odometry
