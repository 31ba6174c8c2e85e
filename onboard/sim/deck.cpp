#include "onboard/sim/deck.hpp"

#include <algorithm>
#include <cmath>
#include <sstream>

#include "common/time.hpp"
#include "onboard/landing/deck_filter.hpp"
#include "onboard/landing/pad_detector.hpp"

namespace stereomap::sim {

using common::Quat;
using common::Rigid3;
using common::Vec3;

namespace {

constexpr double kDeg = M_PI / 180.0;

struct Angles {
  double roll, pitch, yaw, roll_rate, pitch_rate, yaw_rate;
};

Angles anglesAt(const DeckMotionOptions& o, double t) {
  const double wr = 2 * M_PI / o.roll_period_s, wp = 2 * M_PI / o.pitch_period_s;
  return {o.roll_deg * kDeg * std::sin(wr * t),
          o.pitch_deg * kDeg * std::sin(wp * t + 0.7),
          o.yaw_rate_deg_s * kDeg * t,
          o.roll_deg * kDeg * wr * std::cos(wr * t),
          o.pitch_deg * kDeg * wp * std::cos(wp * t + 0.7),
          o.yaw_rate_deg_s * kDeg};
}

// The deck's mean track (no heave): the origin moving at the set speed along its heading.
Vec3 trackAt(const DeckMotionOptions& o, double t) {
  const double w = o.yaw_rate_deg_s * kDeg;
  if (std::abs(w) < 1e-12) return {o.speed_m_s * t, 0, 0};
  return {o.speed_m_s / w * std::sin(w * t), o.speed_m_s / w * (1 - std::cos(w * t)), 0};
}

}  // namespace

Rigid3 DeckMotion::T_world_deck(double t) const {
  const Angles a = anglesAt(options_, t);
  const Quat q = Quat(Eigen::AngleAxisd(a.yaw, Vec3::UnitZ())) *
                 Quat(Eigen::AngleAxisd(a.pitch, Vec3::UnitY())) *
                 Quat(Eigen::AngleAxisd(a.roll, Vec3::UnitX()));
  const double heave = options_.heave_m * std::sin(2 * M_PI * t / options_.heave_period_s);
  return {q, trackAt(options_, t) + Vec3(0, 0, heave)};
}

Vec3 DeckMotion::velocity(double t) const {
  const double yaw = options_.yaw_rate_deg_s * kDeg * t;
  const double w = 2 * M_PI / options_.heave_period_s;
  return {options_.speed_m_s * std::cos(yaw), options_.speed_m_s * std::sin(yaw),
          options_.heave_m * w * std::cos(w * t)};
}

Vec3 DeckMotion::angularRate(double t) const {
  const Angles a = anglesAt(options_, t);
  return landing::bodyRatesFromEuler({a.roll, a.pitch, a.yaw},
                                     {a.roll_rate, a.pitch_rate, a.yaw_rate});
}

Rigid3 DeckMotion::T_deck_pad() { return landing::T_pad_deck().inverse(); }

Rigid3 LandingFlight::T_world_body(double t) const {
  const double s = std::clamp(t / options_.duration_s, 0.0, 1.0);
  const DeckMotionOptions& o = deck_.options();
  const double yaw = o.yaw_rate_deg_s * kDeg * t;
  const Quat heading(Eigen::AngleAxisd(yaw, Vec3::UnitZ()));
  const double closing = 1.0 - 0.9 * s;
  const Vec3 offset(options_.offset_along_m * closing, options_.offset_across_m * closing, 0);
  const double height =
      options_.start_height_m + (options_.end_height_m - options_.start_height_m) * s;
  return {heading * Quat(Eigen::AngleAxisd(options_.heading_deg * kDeg, Vec3::UnitZ())),
          trackAt(o, t) + heading * offset + Vec3(0, 0, height)};
}

Rigid3 LandingFlight::T_body_camera() {
  // Pitched down by 90 deg from the forward camera: the image's x is the body's right.
  return {Quat(Eigen::AngleAxisd(M_PI / 2, Vec3::UnitY())) * common::bodyFromCameraRotation(),
          Vec3::Zero()};
}

Scene makeDeckScene(uint32_t seed, const DeckMarkings& markings) {
  std::vector<SceneBox> boxes = {
      {Vec3(-20, -8, -1), Vec3(20, 8, 0), 0.6f},         // the deck
      {Vec3(-300, -300, -6), Vec3(300, 300, -5), 0.3f},  // the sea
      // What stands on it, clear of the pad (within 2.5 m of the deck's origin): the
      // superstructure at the bow, two containers astern, two crates beside the pad.
      {Vec3(13, -5, 0), Vec3(19, 5, 4), 0.7f},
      {Vec3(-14, 3.5, 0), Vec3(-8, 6, 2.6), 0.5f},
      {Vec3(-14, -6, 0), Vec3(-8, -3.5, 2.6), 0.55f},
      {Vec3(4, -4.5, 0), Vec3(5, -3.5, 1), 0.45f},
      {Vec3(-4.5, 3.5, 0), Vec3(-3.5, 4.5, 1.2), 0.5f},
  };
  Scene scene(std::move(boxes), seed);
  // Pad-frame outlines onto the deck's top (shifted along the pad's x by `dx` metres).
  auto onDeck = [](const std::vector<Vec3>& outline, double dx, SceneMarking marking) {
    for (const Vec3& corner : outline) {
      const Vec3 p = DeckMotion::T_deck_pad() * (corner + Vec3(dx, 0, 0));
      marking.polygon.emplace_back(p.x(), p.y());
    }
    return marking;
  };
  const auto& pad = landing::padModel();
  if (markings.pad) scene.addMarking(onDeck({pad.begin(), pad.end()}, 0, {.box = 0}));
  if (markings.distractor) {
    const std::vector<Vec3> short_t = {Vec3(0, 0, 0), Vec3(3, 0, 0),   Vec3(3, 1, 0),
                                       Vec3(2, 1, 0), Vec3(2, 2.5, 0), Vec3(1, 2.5, 0),
                                       Vec3(1, 1, 0), Vec3(0, 1, 0)};
    scene.addMarking(onDeck(short_t, 5.0, {.box = 0}));
  }
  if (markings.shadow < 1.0) {
    // Pad y from -6 to 2 (the bar and the stem's first metre), across the whole deck width.
    const std::vector<Vec3> half = {Vec3(-30, -6, 0), Vec3(30, -6, 0), Vec3(30, 2, 0),
                                    Vec3(-30, 2, 0)};
    scene.addMarking(
        onDeck(half, 0, {.box = 0, .albedo = static_cast<float>(markings.shadow), .shade = true}));
  }
  return scene;
}

DeckSource::DeckSource(const DeckSourceOptions& options)
    : options_(options),
      scene_(makeDeckScene(options.seed, options.markings)),
      deck_(options.deck),
      flight_(deck_, options.flight),
      renderer_(scene_, camera_, options.render) {}

DeckTruth DeckSource::truthAt(double t) const {
  DeckTruth truth;
  truth.t_s = t;
  truth.T_world_deck = deck_.T_world_deck(t);
  truth.deck_velocity = deck_.velocity(t);
  truth.deck_angular_rate = deck_.angularRate(t);
  const Rigid3 T_world_camera = flight_.T_world_body(t) * LandingFlight::T_body_camera();
  truth.T_camera_pad = T_world_camera.inverse() * truth.T_world_deck * DeckMotion::T_deck_pad();
  truth.distance_m = (truth.T_camera_pad * landing::padCentre()).norm();
  for (const Vec3& corner : landing::padModel()) {
    const auto uv = camera_.project(truth.T_camera_pad * corner);
    if (uv && uv->x() >= 0 && uv->y() >= 0 && uv->x() <= camera_.width - 1 &&
        uv->y() <= camera_.height - 1) {
      ++truth.corners_in_view;
    }
  }
  return truth;
}

std::optional<camera::SourceFrame> DeckSource::next() {
  if (options_.max_frames != 0 && index_ >= options_.max_frames) return std::nullopt;
  const double t = options_.start_s + static_cast<double>(index_) / options_.rate_hz;
  if (t > flight_.options().duration_s) return std::nullopt;
  // The clock starts with the first frame taken (see SimSource::next).
  if (options_.start_stamp_ns == 0) options_.start_stamp_ns = common::nowNs();
  camera::SourceFrame frame;
  frame.index = index_++;
  frame.stamp_ns = options_.start_stamp_ns + static_cast<int64_t>(std::llround(t * 1e9));
  truth_ = truthAt(t);
  // The map is the deck's frame (what stands on the deck stays put in it), the navigation
  // relative to the ship; the deck's pose in the world goes along for its motion.
  frame.T_world_map = truth_.T_world_deck;
  frame.T_map_body = truth_.T_world_deck.inverse() * flight_.T_world_body(t);
  frame.T_body_camera = LandingFlight::T_body_camera();
  // The scene is rigid in the deck's frame: render the camera's pose there.
  const auto T_deck_camera_at = [&](double time) {
    return truthAt(time).T_world_deck.inverse() * flight_.T_world_body(time) *
           LandingFlight::T_body_camera();
  };
  const double half_exposure = 0.5 * options_.render.camera.exposure_s;
  const Rigid3 T_deck_camera = *frame.T_map_body * *frame.T_body_camera;
  StereoFrame rendered = renderer_.render(
      T_deck_camera,
      Renderer::Exposure{T_deck_camera_at(t - half_exposure), T_deck_camera_at(t + half_exposure)});
  frame.left = std::move(rendered.left);
  frame.right = std::move(rendered.right);
  return frame;
}

std::string DeckSource::describe() const {
  std::ostringstream out;
  out << "sim:deck (seed " << options_.seed << ", descent " << flight_.options().start_height_m
      << " -> " << flight_.options().end_height_m << " m over " << flight_.options().duration_s
      << " s, deck at " << options_.deck.speed_m_s << " m/s, " << camera_.width << "x"
      << camera_.height << ")";
  return out.str();
}

}  // namespace stereomap::sim
