// Trajectory metrics, as evo computes them (and KITTI's drift): association by time,
// Umeyama alignment (SE3 or Sim3), absolute trajectory error, relative pose error over frames
// or travelled distance, and KITTI-style drift over path segments.
//
//   auto pairs = associate(gt, est);                 // nearest stamps within 0.01 s
//   auto ape = absoluteError(pairs.ref, pairs.est, Alignment::kSe3);
//   auto drift = kittiDrift(pairs.ref, pairs.est, {10, 20});
#pragma once

#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "common/trajectory.hpp"

namespace stereomap::eval {

struct Stats {
  size_t n = 0;
  double rmse = 0, mean = 0, median = 0, std = 0, min = 0, max = 0, sse = 0;
};
Stats statsOf(const std::vector<double>& values);  // n = 0 for none

// Pose pairs of two trajectories. By time: for every stamp of the shorter trajectory, the
// nearest stamp of the longer one, kept when within max_dt (evo's rule).
struct Associated {
  common::Trajectory ref, est;  // same length, pair by pair
  double max_abs_dt = 0;
};
Associated associate(const common::Trajectory& ref, const common::Trajectory& est,
                     double max_dt = 0.01);
// By index (two KITTI files): the first min(n_ref, n_est) poses.
Associated associateByIndex(const common::Trajectory& ref, const common::Trajectory& est);

enum class Alignment { kNone, kSe3, kSim3 };
// Umeyama (1991): the s, R, t minimising sum |dst - (s R src + t)|^2 (s = 1 unless with_scale):
// Eigen::umeyama, as evo computes it.
struct Similarity {
  double scale = 1;
  common::Quat rotation = common::Quat::Identity();
  common::Vec3 translation = common::Vec3::Zero();
};
Similarity umeyama(const std::vector<common::Vec3>& src, const std::vector<common::Vec3>& dst,
                   bool with_scale);
// est moved by the alignment onto ref (R_a R_est, s R_a t_est + t_a).
common::Trajectory aligned(const common::Trajectory& est, const Similarity& a);

struct AbsoluteError {
  Stats translation;  // metres
  Stats rotation;     // degrees
  Similarity alignment;
  std::vector<double> errors;  // translation error per pair, metres
  common::Trajectory aligned_est;
};
AbsoluteError absoluteError(const common::Trajectory& ref, const common::Trajectory& est,
                            Alignment alignment);

// Index pairs for RPE: (i, i + delta) frames, or evo's "consecutive pairs" by travelled
// distance along the ESTIMATED trajectory (an index each time `delta` metres are reached).
std::vector<std::pair<size_t, size_t>> pairsByFrames(size_t n, size_t delta);
std::vector<std::pair<size_t, size_t>> pairsByPath(const common::Trajectory& est, double delta_m);
struct RelativeError {
  Stats translation;  // metres
  Stats rotation;     // degrees
};
// E = inv(inv(Q_i) Q_j) inv(P_i) P_j per pair (Q reference, P estimate), not aligned.
RelativeError relativeError(const common::Trajectory& ref, const common::Trajectory& est,
                            const std::vector<std::pair<size_t, size_t>>& pairs);

// KITTI's drift: for every start frame (every `step`-th) and segment length L, the first
// frame whose reference path length from the start reaches L; translational error |t(E)| / L
// (percent) and rotational error angle(R(E)) / L (deg per 100 m), averaged over segments.
struct Drift {
  double length_m = 0;  // 0: all lengths together
  size_t segments = 0;
  double translation_percent = 0;
  double rotation_deg_per_100m = 0;
};
// One entry per length that has segments, then the overall average (length 0).
std::vector<Drift> kittiDrift(const common::Trajectory& ref, const common::Trajectory& est,
                              const std::vector<double>& lengths_m, size_t step = 1);
// KITTI's lengths (100..800 m) that fit in the reference path; else 10 m multiples up to half
// of it (short excerpts).
std::vector<double> defaultDriftLengths(const common::Trajectory& ref);
double pathLength(const common::Trajectory& trajectory);
// The farthest any position gets from the first (a standing vehicle's drift).
double largestDisplacement(const common::Trajectory& trajectory);

}  // namespace stereomap::eval
