#include <gtest/gtest.h>

#include <random>

#include "onboard/landing/deck_filter.hpp"
#include "onboard/landing/landing_watch.hpp"
#include "onboard/landing/pad_detector.hpp"
#include "onboard/landing/pad_pose.hpp"
#include "onboard/landing/pad_tracker.hpp"
#include "onboard/sim/deck.hpp"

namespace stereomap::landing {
namespace {

using common::Quat;
using common::Rigid3;
using common::Vec3;

std::array<cv::Point2d, 8> project(const Rigid3& T_camera_pad, const camera::StereoCamera& camera,
                                   double shift = 0.0) {
  std::array<cv::Point2d, 8> out;
  for (int k = 0; k < 8; ++k) {
    Vec3 p = T_camera_pad * padModel()[k];
    p.x() -= shift;
    const auto uv = *camera.project(p);
    out[k] = {uv.x(), uv.y()};
  }
  return out;
}

Rigid3 randomView(std::mt19937& rng, double distance) {
  std::uniform_real_distribution<double> tilt(-0.3, 0.3), spin(-M_PI, M_PI), lateral(-2, 2);
  const Quat q = Quat(Eigen::AngleAxisd(spin(rng), Vec3::UnitZ())) *
                 Quat(Eigen::AngleAxisd(tilt(rng), Vec3::UnitX())) *
                 Quat(Eigen::AngleAxisd(tilt(rng), Vec3::UnitY()));
  // The pad's centre ahead of the camera at `distance`.
  const Vec3 centre(lateral(rng), lateral(rng), distance);
  return {q, centre - q * padCentre()};
}

// Without noise the patent's linear solution and the default solve are exact.
TEST(PadPose, BothModesAreExactOnNoiseFreeCorners) {
  std::mt19937 rng(3);
  const camera::StereoCamera camera;
  for (int trial = 0; trial < 50; ++trial) {
    const Rigid3 truth = randomView(rng, 8 + trial * 0.4);
    const auto left = project(truth, camera);
    const auto right = project(truth, camera, camera.baseline);
    const auto linear = patentLinearPose(left, camera);
    ASSERT_TRUE(linear) << trial;
    EXPECT_LT(linear->rotation.angularDistance(truth.rotation), 1e-6) << trial;
    EXPECT_LT((linear->translation - truth.translation).norm(), 1e-6) << trial;
    for (const PoseMode mode : {PoseMode::kDefault, PoseMode::kPatent}) {
      const PadPose pose = estimatePadPose(left, right, camera, {.mode = mode});
      ASSERT_TRUE(pose) << pose.reason;
      EXPECT_LT(pose.T_camera_pad.rotation.angularDistance(truth.rotation), 1e-6) << trial;
      EXPECT_LT((pose.T_camera_pad.translation - truth.translation).norm(), 1e-5) << trial;
    }
  }
}

// Corners that are not the pad's (two swapped) give a pose whose reprojection error is large:
// refused, in both modes.
TEST(PadPose, CornersThatAreNotThePadsAreRefused) {
  std::mt19937 rng(4);
  const camera::StereoCamera camera;
  auto left = project(randomView(rng, 10), camera);
  std::swap(left[1], left[5]);
  for (const PoseMode mode : {PoseMode::kDefault, PoseMode::kPatent}) {
    const PadPose pose = estimatePadPose(left, std::nullopt, camera, {.mode = mode});
    EXPECT_FALSE(pose);
    EXPECT_FALSE(pose.reason.empty());
  }
}

// The corners are named by the T's structure whatever the pad's rotation in the image; the
// patent's rule (smallest y first) gets an upright pad right and an upside-down one wrong.
TEST(PadCorners, NamedByStructureAtAnyRotation) {
  std::mt19937 rng(5);
  const camera::StereoCamera camera;
  for (int trial = 0; trial < 40; ++trial) {
    const auto truth = project(randomView(rng, 12), camera);
    std::vector<cv::Point2d> polygon(truth.begin(), truth.end());
    std::rotate(polygon.begin(), polygon.begin() + trial % 8, polygon.end());
    const auto named = orderTCorners(polygon);
    ASSERT_TRUE(named);
    for (int k = 0; k < 8; ++k) EXPECT_LT(cv::norm((*named)[k] - truth[k]), 1e-9) << trial;
  }
  const Rigid3 upright{Quat::Identity(), Vec3(0, 0, 10.0) - padCentre()};
  const auto seen = project(upright, camera);
  std::vector<cv::Point2d> polygon(seen.begin(), seen.end());
  std::rotate(polygon.begin(), polygon.begin() + 3, polygon.end());
  EXPECT_LT(cv::norm(patentOrder(polygon)[0] - seen[0]), 1e-9);
  const Rigid3 upside_down{Quat(Eigen::AngleAxisd(M_PI, Vec3::UnitZ())), Vec3(1.5, 2.0, 10.0)};
  const auto turned = project(upside_down, camera);
  std::vector<cv::Point2d> turned_polygon(turned.begin(), turned.end());
  EXPECT_GT(cv::norm(patentOrder(turned_polygon)[0] - turned[0]), 10.0);
  ASSERT_TRUE(orderTCorners(turned_polygon));
  EXPECT_LT(cv::norm((*orderTCorners(turned_polygon))[0] - turned[0]), 1e-9);
}

// Rendered frames of the descent: the pad is found, its corners land near their true
// projections.
TEST(PadDetector, FindsThePadOnRenderedDeckFrames) {
  for (const double start : {4.0, 25.0, 40.0}) {
    sim::DeckSource source({.max_frames = 1, .start_s = start});
    const auto frame = source.next();
    ASSERT_TRUE(frame);
    const auto found = detectPad(frame->left);
    ASSERT_TRUE(found) << "at " << source.truth().distance_m << " m: " << found.reason;
    double worst = 0;
    for (int k = 0; k < 8; ++k) {
      const auto uv = *source.camera().project(source.truth().T_camera_pad * padModel()[k]);
      worst = std::max(worst, std::hypot(found.corners[k].x - uv.x(), found.corners[k].y - uv.y()));
    }
    std::printf("at %.1f m: worst corner %.3f px, shape error %.4f, contrast %.0f\n",
                source.truth().distance_m, worst, found.shape_error, found.contrast);
    EXPECT_LT(worst, 1.0) << "at " << source.truth().distance_m << " m";
  }
}

// What one rendered frame gives: the tracker's state and, when it tracks, the default pose's
// error (% of distance, degrees).
struct Seen {
  TrackState state;
  std::string reason;
  bool published = false;
  double position_pct = 0, attitude_deg = 0, distance_m = 0, corner_px = 0;
};

// Runs the product's chain (LandingWatch) over the frames.
std::vector<Seen> follow(sim::DeckSourceOptions options) {
  sim::DeckSource source(options);
  LandingWatch watch(source.camera());
  std::vector<Seen> out;
  while (const auto frame = source.next()) {
    const auto& truth = source.truth();
    const LandingReport& seen =
        watch.update(truth.t_s, frame->left, frame->right, *frame->T_map_body,
                     *frame->T_body_camera, frame->T_world_map.value_or(Rigid3{}));
    Seen s{seen.state, seen.reason};
    s.distance_m = truth.distance_m;
    if (seen.state == TrackState::kTracking) {
      double squared = 0;
      for (int k = 0; k < 8; ++k) {
        const auto uv = *source.camera().project(truth.T_camera_pad * padModel()[k]);
        squared += std::pow(seen.left.corners[k].x - uv.x(), 2) +
                   std::pow(seen.left.corners[k].y - uv.y(), 2);
      }
      s.corner_px = std::sqrt(squared / 8);
    }
    s.published = seen.has_pose;
    if (seen.has_pose) {
      const Rigid3& pose = seen.pose.T_camera_pad;
      s.position_pct =
          100 * (pose * padCentre() - truth.T_camera_pad * padCentre()).norm() / truth.distance_m;
      s.attitude_deg = pose.rotation.angularDistance(truth.T_camera_pad.rotation) * 180 / M_PI;
    }
    out.push_back(s);
  }
  return out;
}

// The descent's first frames: locked at once (within 3 frames of the whole pad in view),
// followed from then on with corners on their true projections and poses within 1 % of the
// distance.
TEST(PadTracker, LocksAtOnceAndFollowsThePad) {
  const auto seen = follow({.max_frames = 20, .start_s = 10});
  int first = -1;
  for (size_t i = 0; i < seen.size() && first < 0; ++i) {
    if (seen[i].state == TrackState::kTracking) first = static_cast<int>(i);
  }
  ASSERT_GE(first, 0);
  EXPECT_LE(first, 2);
  for (size_t i = static_cast<size_t>(first); i < seen.size(); ++i) {
    EXPECT_EQ(seen[i].state, TrackState::kTracking) << i << ": " << seen[i].reason;
    EXPECT_LT(seen[i].corner_px, 0.6) << i;
    EXPECT_TRUE(seen[i].published) << i;
    EXPECT_LT(seen[i].position_pct, 1.0) << i;
  }
}

// A deck without the pad: SEARCHING, with a reason, never a pose.
TEST(PadTracker, ADeckWithoutThePadIsSearchedWithAReason) {
  for (const auto& s : follow({.max_frames = 3, .start_s = 20, .markings = {.pad = false}})) {
    EXPECT_EQ(s.state, TrackState::kSearching);
    EXPECT_FALSE(s.reason.empty());
    EXPECT_FALSE(s.published);
  }
}

// A T-like mark beside the pad (a shorter stem) is never taken for it.
TEST(PadTracker, ATLikeMarkBesideThePadIsNotThePad) {
  for (const auto& s : follow({.max_frames = 4, .start_s = 15, .markings = {.distractor = true}})) {
    EXPECT_EQ(s.state, TrackState::kTracking) << s.reason;
    EXPECT_LT(s.corner_px, 0.6);
    EXPECT_LT(s.position_pct, 1.0);
  }
  // The distractor alone: nothing found.
  for (const auto& s :
       follow({.max_frames = 2, .start_s = 15, .markings = {.pad = false, .distractor = true}})) {
    EXPECT_NE(s.state, TrackState::kTracking);
    EXPECT_NE(s.reason.find("proportions"), std::string::npos) << s.reason;
  }
}

// A strong shadow over half the pad (a third of the light): still found, still accurate.
TEST(PadTracker, AStrongShadowOverHalfThePad) {
  for (const auto& s : follow({.max_frames = 4, .start_s = 25, .markings = {.shadow = 0.35}})) {
    EXPECT_EQ(s.state, TrackState::kTracking) << s.reason;
    EXPECT_LT(s.corner_px, 0.6);
    EXPECT_LT(s.position_pct, 1.0);
    EXPECT_LT(s.attitude_deg, 2.0) << s.distance_m << " m, corners " << s.corner_px << " px";
  }
}

// The last metres: the pad leaves the image. The tracker says so (LOST, with a reason) and
// no pose it publishes is off by more than 5 % of the distance.
TEST(PadTracker, ThePadLeavingTheImageIsLostAndNoWrongPoseIsPublished) {
  const auto seen = follow({.start_s = 52});
  ASSERT_FALSE(seen.empty());
  int lost = 0;
  for (const auto& s : seen) {
    if (s.published) {
      EXPECT_LT(s.position_pct, 5.0) << s.distance_m;
    }
    lost += s.state == TrackState::kLost;
  }
  EXPECT_GT(lost, 0);
  EXPECT_EQ(seen.back().state, TrackState::kLost);
  EXPECT_FALSE(seen.back().reason.empty());
}

// The deck filter on measurements of a known motion (heave 0.5 m at 0.1 Hz, roll 5 deg, 5 m/s
// forward) with 1 cm and 0.3 deg of noise at 10 Hz: heave rate within 0.1 m/s RMS after a
// second.
TEST(DeckFilter, FollowsAHeavingRollingDeck) {
  sim::DeckMotion motion;
  DeckFilter filter;
  std::mt19937 rng(8);
  std::normal_distribution<double> noise;
  double squared = 0;
  int n = 0;
  for (int k = 0; k < 600; ++k) {
    const double t = k * 0.1;
    const Rigid3 T_map_deck = motion.T_world_deck(t);
    const Vec3 small(noise(rng), noise(rng), noise(rng));
    const Rigid3 measured{
        T_map_deck.rotation *
            Quat(Eigen::AngleAxisd(0.3 * M_PI / 180 * small.norm(), small.normalized())),
        T_map_deck.translation + 0.01 * Vec3(noise(rng), noise(rng), noise(rng))};
    Mat6 covariance = Mat6::Zero();
    covariance.diagonal() << Vec3::Constant(std::pow(0.3 * M_PI / 180, 2)), Vec3::Constant(1e-4);
    const auto& estimate = filter.update(t, measured * T_pad_deck().inverse(), covariance);
    if (t < 1.0) continue;
    squared += std::pow(estimate.velocity.z() - motion.velocity(t).z(), 2);
    ++n;
  }
  const double rms = std::sqrt(squared / n);
  std::printf("heave rate error %.3f m/s RMS\n", rms);
  EXPECT_LT(rms, 0.1);
  EXPECT_LT((filter.estimate().velocity.head<2>() - motion.velocity(59.9).head<2>()).norm(), 0.2);
}

}  // namespace
}  // namespace stereomap::landing
