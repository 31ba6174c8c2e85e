#include "onboard/eval/metrics.hpp"

#include <Eigen/Geometry>

#include <algorithm>
#include <cmath>
#include <numeric>

namespace stereomap::eval {

using common::Quat;
using common::Rigid3;
using common::Trajectory;
using common::Vec3;

namespace {
constexpr double kDegrees = 180.0 / M_PI;

double angleDegrees(const Quat& q) { return Eigen::AngleAxisd(q.normalized()).angle() * kDegrees; }
}  // namespace

Stats statsOf(const std::vector<double>& values) {
  Stats s;
  s.n = values.size();
  if (values.empty()) return s;
  std::vector<double> sorted = values;
  std::sort(sorted.begin(), sorted.end());
  s.min = sorted.front();
  s.max = sorted.back();
  const size_t mid = s.n / 2;
  s.median = s.n % 2 == 1 ? sorted[mid] : 0.5 * (sorted[mid - 1] + sorted[mid]);
  for (double v : values) {
    s.sse += v * v;
    s.mean += v;
  }
  s.mean /= static_cast<double>(s.n);
  s.rmse = std::sqrt(s.sse / static_cast<double>(s.n));
  double var = 0;
  for (double v : values) var += (v - s.mean) * (v - s.mean);
  s.std = std::sqrt(var / static_cast<double>(s.n));
  return s;
}

Associated associate(const Trajectory& ref, const Trajectory& est, double max_dt) {
  const bool ref_shorter = ref.size() <= est.size();
  const Trajectory& shorter = ref_shorter ? ref : est;
  const Trajectory& longer = ref_shorter ? est : ref;
  std::vector<size_t> order(longer.size());
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(),
                   [&](size_t a, size_t b) { return longer[a].t < longer[b].t; });
  Associated out;
  if (longer.empty()) return out;
  for (const auto& pose : shorter) {
    auto it = std::lower_bound(order.begin(), order.end(), pose.t,
                               [&](size_t i, double t) { return longer[i].t < t; });
    // evo's pick between the neighbours: the left one on a tie.
    size_t pick = 0;
    if (order.size() > 1) {
      const size_t pos = std::clamp<size_t>(it - order.begin(), 1, order.size() - 1);
      const double left = longer[order[pos - 1]].t, right = longer[order[pos]].t;
      pick = std::abs(pose.t - left) <= std::abs(right - pose.t) ? pos - 1 : pos;
    }
    const auto& match = longer[order[pick]];
    const double dt = std::abs(match.t - pose.t);
    if (dt > max_dt) continue;
    out.max_abs_dt = std::max(out.max_abs_dt, dt);
    out.ref.push_back(ref_shorter ? pose : match);
    out.est.push_back(ref_shorter ? match : pose);
  }
  return out;
}

Associated associateByIndex(const Trajectory& ref, const Trajectory& est) {
  const size_t n = std::min(ref.size(), est.size());
  return {Trajectory(ref.begin(), ref.begin() + n), Trajectory(est.begin(), est.begin() + n), 0};
}

Similarity umeyama(const std::vector<Vec3>& src, const std::vector<Vec3>& dst, bool with_scale) {
  Eigen::Matrix3Xd from(3, src.size()), to(3, dst.size());
  for (size_t i = 0; i < src.size(); ++i) from.col(static_cast<Eigen::Index>(i)) = src[i];
  for (size_t i = 0; i < dst.size(); ++i) to.col(static_cast<Eigen::Index>(i)) = dst[i];
  // Eigen divides by the source's spread for the scale: none (one point, or all alike)
  // means no scale to find.
  const bool scaled = with_scale && (from.colwise() - from.rowwise().mean()).squaredNorm() > 0;
  const Eigen::Matrix4d T = Eigen::umeyama(from, to, scaled);
  const Eigen::Matrix3d sR = T.topLeftCorner<3, 3>();
  Similarity a;
  a.scale = scaled ? sR.col(0).norm() : 1.0;
  // A reference that does not move (scale 0) has no rotation to find.
  a.rotation = a.scale > 0 ? Quat(sR / a.scale).normalized() : Quat::Identity();
  a.translation = T.topRightCorner<3, 1>();
  return a;
}

Trajectory aligned(const Trajectory& est, const Similarity& a) {
  Trajectory out = est;
  for (auto& p : out) {
    p.pose.rotation = (a.rotation * p.pose.rotation).normalized();
    p.pose.translation = a.scale * (a.rotation * p.pose.translation) + a.translation;
  }
  return out;
}

AbsoluteError absoluteError(const Trajectory& ref, const Trajectory& est, Alignment alignment) {
  AbsoluteError out;
  if (alignment != Alignment::kNone && ref.size() >= 3) {
    std::vector<Vec3> src, dst;
    for (size_t i = 0; i < ref.size(); ++i) {
      src.push_back(est[i].pose.translation);
      dst.push_back(ref[i].pose.translation);
    }
    out.alignment = umeyama(src, dst, alignment == Alignment::kSim3);
  }
  out.aligned_est = aligned(est, out.alignment);
  std::vector<double> rotation;
  for (size_t i = 0; i < ref.size(); ++i) {
    out.errors.push_back((ref[i].pose.translation - out.aligned_est[i].pose.translation).norm());
    rotation.push_back(
        angleDegrees(ref[i].pose.rotation.conjugate() * out.aligned_est[i].pose.rotation));
  }
  out.translation = statsOf(out.errors);
  out.rotation = statsOf(rotation);
  return out;
}

std::vector<std::pair<size_t, size_t>> pairsByFrames(size_t n, size_t delta) {
  std::vector<std::pair<size_t, size_t>> pairs;
  for (size_t i = 0; delta > 0 && i + delta < n; ++i) pairs.emplace_back(i, i + delta);
  return pairs;
}

std::vector<std::pair<size_t, size_t>> pairsByPath(const Trajectory& est, double delta_m) {
  std::vector<size_t> marks;
  double travelled = 0;
  for (size_t k = 1; k < est.size(); ++k) {
    travelled += (est[k].pose.translation - est[k - 1].pose.translation).norm();
    if (travelled >= delta_m) {
      marks.push_back(k);
      travelled = 0;
    }
  }
  std::vector<std::pair<size_t, size_t>> pairs;
  for (size_t i = 1; i < marks.size(); ++i) pairs.emplace_back(marks[i - 1], marks[i]);
  return pairs;
}

namespace {
// inv(inv(Q_i) Q_j) inv(P_i) P_j
Rigid3 relativeErrorPose(const Trajectory& ref, const Trajectory& est, size_t i, size_t j) {
  const Rigid3 q = ref[i].pose.inverse() * ref[j].pose;
  const Rigid3 p = est[i].pose.inverse() * est[j].pose;
  return q.inverse() * p;
}
}  // namespace

RelativeError relativeError(const Trajectory& ref, const Trajectory& est,
                            const std::vector<std::pair<size_t, size_t>>& pairs) {
  std::vector<double> translation, rotation;
  for (const auto& [i, j] : pairs) {
    const Rigid3 e = relativeErrorPose(ref, est, i, j);
    translation.push_back(e.translation.norm());
    rotation.push_back(angleDegrees(e.rotation));
  }
  return {statsOf(translation), statsOf(rotation)};
}

double pathLength(const Trajectory& trajectory) {
  double length = 0;
  for (size_t k = 1; k < trajectory.size(); ++k) {
    length += (trajectory[k].pose.translation - trajectory[k - 1].pose.translation).norm();
  }
  return length;
}

double largestDisplacement(const Trajectory& trajectory) {
  double largest = 0;
  for (const auto& p : trajectory) {
    largest = std::max(largest, (p.pose.translation - trajectory.front().pose.translation).norm());
  }
  return largest;
}

std::vector<double> defaultDriftLengths(const Trajectory& ref) {
  const double path = pathLength(ref);
  std::vector<double> lengths;
  for (double l = 100; l <= 800 && l < path; l += 100) lengths.push_back(l);
  if (lengths.empty()) {
    for (double l = 10; l <= path / 2; l += 10) lengths.push_back(l);
  }
  if (lengths.empty() && path > 0) lengths.push_back(path / 2);
  return lengths;
}

std::vector<Drift> kittiDrift(const Trajectory& ref, const Trajectory& est,
                              const std::vector<double>& lengths_m, size_t step) {
  std::vector<double> distance(ref.size(), 0.0);  // reference path length from frame 0
  for (size_t k = 1; k < ref.size(); ++k) {
    distance[k] = distance[k - 1] + (ref[k].pose.translation - ref[k - 1].pose.translation).norm();
  }
  std::vector<Drift> out;
  Drift all;
  for (const double length : lengths_m) {
    Drift d;
    d.length_m = length;
    for (size_t i = 0; i < ref.size(); i += std::max<size_t>(step, 1)) {
      const auto last =
          std::lower_bound(distance.begin() + i, distance.end(), distance[i] + length);
      if (last == distance.end()) break;
      const Rigid3 e = relativeErrorPose(ref, est, i, last - distance.begin());
      d.translation_percent += e.translation.norm() / length * 100;
      d.rotation_deg_per_100m += angleDegrees(e.rotation) / length * 100;
      ++d.segments;
    }
    if (d.segments == 0) continue;
    all.translation_percent += d.translation_percent;
    all.rotation_deg_per_100m += d.rotation_deg_per_100m;
    all.segments += d.segments;
    d.translation_percent /= static_cast<double>(d.segments);
    d.rotation_deg_per_100m /= static_cast<double>(d.segments);
    out.push_back(d);
  }
  if (all.segments > 0) {
    all.translation_percent /= static_cast<double>(all.segments);
    all.rotation_deg_per_100m /= static_cast<double>(all.segments);
    out.push_back(all);
  }
  return out;
}

}  // namespace stereomap::eval
