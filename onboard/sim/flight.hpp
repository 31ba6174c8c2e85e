// A scripted flight through the simulated room: a closed loop (an ellipse around the room's
// centre) with the height and heading changing smoothly, as T_map_body (FLU body frame)
// over time. The camera is mounted looking forward, pitched down a little.
#pragma once

#include "common/geometry.hpp"

namespace stereomap::sim {

struct FlightOptions {
  double radius_x = 3.0;  // metres, ellipse semi-axes around the map origin
  double radius_y = 2.4;
  double height = 1.4;              // mean height above the floor, metres
  double height_swing = 0.3;        // +- metres, two cycles per loop
  double period_s = 40.0;           // one loop
  double look_outward = 0.5;        // radians the heading is turned from the path towards the walls
  double camera_pitch_down = 0.15;  // radians
};

class Flight {
 public:
  explicit Flight(FlightOptions options = {});
  common::Rigid3 T_map_body(double t_s) const;
  // The fixed camera mount: T_body_camera (OpenCV camera axes).
  common::Rigid3 T_body_camera() const;
  common::Rigid3 T_map_camera(double t_s) const { return T_map_body(t_s) * T_body_camera(); }
  const FlightOptions& options() const { return options_; }

 private:
  FlightOptions options_;
};

}  // namespace stereomap::sim
