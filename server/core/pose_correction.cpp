#include "server/core/pose_correction.hpp"

#include <algorithm>

namespace stereomap::core {

using common::ErrorCode;
using common::makeError;
using common::Rigid3;

namespace {

bool rigid(const Rigid3& T) {
  return common::isUnitQuaternion(T.rotation) && T.translation.allFinite();
}

bool byStamp(const StampedBodyPose& a, const StampedBodyPose& b) { return a.stamp_ns < b.stamp_ns; }

}  // namespace

common::Result<PoseCorrection> PoseCorrection::create(std::vector<StampedBodyPose> sent,
                                                      std::vector<StampedBodyPose> keyframes) {
  if (keyframes.empty())
    return makeError(ErrorCode::kInvalidArgument, "a correction without keyframes");
  for (const auto& list : {&sent, &keyframes}) {
    for (const auto& p : *list) {
      if (!rigid(p.T_map_body)) {
        return makeError(ErrorCode::kInvalidArgument,
                         "a pose of the correction is not a rigid transform");
      }
    }
  }
  std::sort(sent.begin(), sent.end(), byStamp);
  std::sort(keyframes.begin(), keyframes.end(), byStamp);
  if (std::adjacent_find(keyframes.begin(), keyframes.end(), [](const auto& a, const auto& b) {
        return a.stamp_ns == b.stamp_ns;
      }) != keyframes.end()) {
    return makeError(ErrorCode::kInvalidArgument, "a keyframe is corrected twice");
  }
  PoseCorrection correction;
  correction.sent_ = std::move(sent);
  // A keyframe whose pose never arrived (lost on the link, or still on its way) cannot say
  // how far the sent poses were off: it is left out, and its neighbours correct its stretch.
  for (const auto& k : keyframes) {
    const auto it = std::lower_bound(correction.sent_.begin(), correction.sent_.end(), k, byStamp);
    if (it == correction.sent_.end() || it->stamp_ns != k.stamp_ns) continue;
    correction.keyframes_.push_back(k);
    correction.sent_at_keyframe_.push_back(it->T_map_body);
  }
  if (correction.keyframes_.empty()) {
    return makeError(ErrorCode::kInvalidArgument,
                     "none of the " + std::to_string(keyframes.size()) +
                         " corrected keyframes is a pose the vehicle sent");
  }
  return correction;
}

Rigid3 PoseCorrection::sentAt(int64_t stamp_ns) const {
  // The sent pose at a stamp, interpolated between the neighbouring sent poses (clouds and
  // poses of one frame share a stamp; anything else is between two frames).
  const StampedBodyPose key{stamp_ns, {}};
  const auto after = std::lower_bound(sent_.begin(), sent_.end(), key, byStamp);
  if (after == sent_.end()) return sent_.back().T_map_body;
  if (after->stamp_ns == stamp_ns || after == sent_.begin()) return after->T_map_body;
  const auto before = after - 1;
  const double s = static_cast<double>(stamp_ns - before->stamp_ns) /
                   static_cast<double>(after->stamp_ns - before->stamp_ns);
  return common::interpolate(before->T_map_body, after->T_map_body, s);
}

Rigid3 PoseCorrection::delta(int64_t stamp_ns) const {
  const Rigid3 sent = sent_.empty() ? Rigid3::identity() : sentAt(stamp_ns);
  // The pose as corrected through keyframe i, keeping the motion since it as sent.
  auto through = [&](size_t i) {
    return keyframes_[i].T_map_body * sent_at_keyframe_[i].inverse() * sent;
  };
  const StampedBodyPose key{stamp_ns, {}};
  const auto after = std::lower_bound(keyframes_.begin(), keyframes_.end(), key, byStamp);
  Rigid3 corrected;
  if (after == keyframes_.end()) {
    corrected = through(keyframes_.size() - 1);
  } else if (after == keyframes_.begin() || after->stamp_ns == stamp_ns) {
    corrected = through(static_cast<size_t>(after - keyframes_.begin()));
  } else {
    const size_t b = static_cast<size_t>(after - keyframes_.begin());
    const size_t a = b - 1;
    const double s = static_cast<double>(stamp_ns - keyframes_[a].stamp_ns) /
                     static_cast<double>(keyframes_[b].stamp_ns - keyframes_[a].stamp_ns);
    corrected = common::interpolate(through(a), through(b), s);
  }
  return corrected * sent.inverse();
}

}  // namespace stereomap::core
