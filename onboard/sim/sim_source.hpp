// The simulated vehicle as a FrameSource: renders the scripted flight through a seeded room
// at a fixed frame rate, with ground-truth poses.
#pragma once

#include "onboard/camera/frame_source.hpp"
#include "onboard/sim/flight.hpp"
#include "onboard/sim/renderer.hpp"
#include "onboard/sim/scene.hpp"

namespace stereomap::sim {

struct SimSourceOptions {
  uint32_t seed = 1;
  double rate_hz = 10.0;       // simulated time between frames is 1 / rate_hz
  uint64_t max_frames = 0;     // 0: unlimited (the flight loops)
  int64_t start_stamp_ns = 0;  // stamp of frame 0; 0 = when frame 0 is taken
  // Where in the flight frame 0 is, seconds (the flight loops every FlightOptions::period_s);
  // stamps still start at start_stamp_ns.
  double start_s = 0;
  // The room's size (the seed places its obstacles): sim flies 12 x 10 m, sim:hall 18 x 7 m,
  // a place no flight of the other overlaps.
  double room_length = 12.0, room_width = 10.0;
  RenderOptions render;
  FlightOptions flight;
};

class SimSource : public camera::FrameSource {
 public:
  explicit SimSource(const SimSourceOptions& options);
  const camera::StereoCamera& camera() const override { return camera_; }
  std::optional<camera::SourceFrame> next() override;
  std::string describe() const override;
  bool live() const override { return true; }
  void skip(uint64_t frames) override { index_ += frames; }

  const Scene& scene() const { return scene_; }
  const Flight& flight() const { return flight_; }

 private:
  SimSourceOptions options_;
  camera::StereoCamera camera_;
  Scene scene_;
  Flight flight_;
  Renderer renderer_;
  uint64_t index_ = 0;
};

}  // namespace stereomap::sim
