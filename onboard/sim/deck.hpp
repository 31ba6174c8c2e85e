// A ship's deck to land on (the landing patent, section 2 of ../shared/PAPERS.md): a grey
// textured deck with the black T-shaped pad, moving as a ship does (forward speed, heave,
// roll, pitch, a slow turn), and a vehicle above it descending with a downward-looking
// camera. The scene is rigid in the deck's frame, so it is rendered there: exact images, and
// exact truth of the pad's pose in the camera and of the deck's motion. Frames are in the
// deck's frame (SourceFrame::T_map_body relative to the ship, as a ship-relative navigation
// gives it), with the deck's pose in the world beside (SourceFrame::T_world_map).
//
//   DeckSource source({.seed = 1});             // 640x480 at 10 Hz, the typical camera
//   while (auto frame = source.next()) { const DeckTruth& truth = source.truth(); ... }
#pragma once

#include <array>

#include "onboard/camera/frame_source.hpp"
#include "onboard/sim/renderer.hpp"
#include "onboard/sim/scene.hpp"

namespace stereomap::sim {

struct DeckMotionOptions {
  double speed_m_s = 5.0;  // forward, along the world x
  double heave_m = 0.5;    // +-, about 0.1 Hz
  double heave_period_s = 10.0;
  double roll_deg = 5.0;  // +-
  double roll_period_s = 9.0;
  double pitch_deg = 3.0;  // +-
  double pitch_period_s = 7.0;
  double yaw_rate_deg_s = 0.5;  // the slow turn
};

// The deck's pose in the world (z up) and its motion: velocity (world) and angular rate
// (deck axes) from the closed form.
class DeckMotion {
 public:
  explicit DeckMotion(DeckMotionOptions options = {}) : options_(options) {}
  common::Rigid3 T_world_deck(double t_s) const;
  common::Vec3 velocity(double t_s) const;     // world, m/s
  common::Vec3 angularRate(double t_s) const;  // deck axes, rad/s
  // The pad on the deck: its centre at the deck's origin, its z down into the deck.
  static common::Rigid3 T_deck_pad();
  const DeckMotionOptions& options() const { return options_; }

 private:
  DeckMotionOptions options_;
};

struct LandingFlightOptions {
  double duration_s = 60.0;
  double start_height_m = 30.0;  // above the deck's mean level
  double end_height_m = 2.0;
  // The vehicle's offset from the pad's centre across and along the deck, at the start; it
  // closes to a tenth of it by the end.
  double offset_across_m = 3.0;
  double offset_along_m = -2.0;
  double heading_deg = 10.0;  // turned from the deck's heading (0: the stem along the image x)
};

// The vehicle: it follows the deck's mean track (not its heave or tilt), descending, camera
// looking straight down.
class LandingFlight {
 public:
  LandingFlight(const DeckMotion& deck, LandingFlightOptions options = {})
      : deck_(deck), options_(options) {}
  common::Rigid3 T_world_body(double t_s) const;
  static common::Rigid3 T_body_camera();
  const LandingFlightOptions& options() const { return options_; }

 private:
  const DeckMotion& deck_;
  LandingFlightOptions options_;
};

// What is painted on the deck, and the light on it.
struct DeckMarkings {
  bool pad = true;
  // A second, T-like mark beside the pad (a T with a short stem: bar 3 x 1 m, stem 1 x 1.5 m).
  bool distractor = false;
  // A shadow over the half of the pad on the bar's side (and the deck around it), multiplying
  // the light by this (1: none).
  double shadow = 1.0;
};

// The deck scene in the deck frame: the deck (40 x 16 m, its top at z = 0) with the T painted
// on it, what stands on it (a superstructure, two containers, two crates; none within 2.5 m
// of the pad's centre), and the sea below.
Scene makeDeckScene(uint32_t seed, const DeckMarkings& markings = {});

struct DeckTruth {
  double t_s = 0;
  common::Rigid3 T_camera_pad;  // the left camera's view of the pad
  common::Rigid3 T_world_deck;
  common::Vec3 deck_velocity;  // world
  common::Vec3 deck_angular_rate;
  double distance_m = 0;    // camera to the pad's centre
  int corners_in_view = 0;  // of the 8, inside the left image
};

struct DeckSourceOptions {
  uint32_t seed = 1;
  double rate_hz = 10.0;
  uint64_t max_frames = 0;     // 0: the whole descent
  int64_t start_stamp_ns = 0;  // stamp of frame 0; 0 = when frame 0 is taken
  double start_s = 0;          // where in the descent to begin
  DeckMarkings markings;
  // The typical camera (issue 19: noise and blur on, the camera presets where they exist).
  RenderOptions render{.max_depth = 80.0, .camera = CameraModel::typical(), .supersample = 3};
  DeckMotionOptions deck;
  LandingFlightOptions flight;
};

class DeckSource : public camera::FrameSource {
 public:
  explicit DeckSource(const DeckSourceOptions& options);
  const camera::StereoCamera& camera() const override { return camera_; }
  std::optional<camera::SourceFrame> next() override;
  std::string describe() const override;
  bool live() const override { return true; }
  void skip(uint64_t frames) override { index_ += frames; }
  // The truth of the frame `next` returned last.
  const DeckTruth& truth() const { return truth_; }
  DeckTruth truthAt(double t_s) const;
  const Scene& scene() const { return scene_; }
  const DeckMotion& deck() const { return deck_; }

 private:
  DeckSourceOptions options_;
  camera::StereoCamera camera_;
  Scene scene_;
  DeckMotion deck_;
  LandingFlight flight_;
  Renderer renderer_;
  uint64_t index_ = 0;
  DeckTruth truth_;
};

}  // namespace stereomap::sim
