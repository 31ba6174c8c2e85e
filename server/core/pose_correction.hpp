// What a vehicle's pose graph changes in poses it has already sent (issue 18): for some of
// its keyframes (by stamp) the pose it now believes. PoseCorrection turns that into the
// correction of any sample sent at any stamp, so that the server can fuse the session's
// journaled clouds again where they belong.
//
// Between two corrected keyframes a and b, the sample keeps its motion relative to each as
// sent (the odometry is good over short stretches): T(s) = T_new(k) T_sent(k)^-1 T_sent(s)
// for k = a and for k = b, blended by time (position linearly, attitude by slerp). Before the
// first keyframe and after the last, that keyframe alone. Poses are blended near the vehicle,
// not as map-frame deltas, whose rotation about the map origin would swing a vehicle far from
// it.
//
//   auto correction = PoseCorrection::create(sent_poses, keyframes);
//   T_map_camera_new = correction->delta(stamp) * T_map_camera_sent;
#pragma once

#include <cstdint>
#include <vector>

#include "common/geometry.hpp"
#include "common/result.hpp"

namespace stereomap::core {

struct StampedBodyPose {
  int64_t stamp_ns = 0;
  common::Rigid3 T_map_body;
};

class PoseCorrection {
 public:
  // `sent`: every pose the vehicle sent (any order); `keyframes`: the corrected ones, by the
  // stamps of sent poses (keyframes at other stamps are left out). Refuses an empty
  // correction, one with no known stamp, repeated keyframes and poses that are not rigid
  // transforms.
  static common::Result<PoseCorrection> create(std::vector<StampedBodyPose> sent,
                                               std::vector<StampedBodyPose> keyframes);

  // The map-frame correction of a sample sent at `stamp_ns` with a pose near the vehicle's
  // (its body or a sensor on it): new = delta * sent.
  common::Rigid3 delta(int64_t stamp_ns) const;

 private:
  std::vector<StampedBodyPose> sent_;       // by stamp
  std::vector<StampedBodyPose> keyframes_;  // by stamp
  std::vector<common::Rigid3> sent_at_keyframe_;
  common::Rigid3 sentAt(int64_t stamp_ns) const;
};

}  // namespace stereomap::core
