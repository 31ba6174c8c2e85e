// The pose-graph paper's simulated ground test (section 3 of ../shared/PAPERS.md), as
// stereomap-bench-posegraph and the tests run it. Our reading of the set-up, since the paper
// gives only its outline (docs/BENCHMARKS.md says more):
//  - a 400 mm vehicle carrying 4 markers; attitude (roll, pitch, yaw) each 0 -> 30 deg -> 0 as
//    a sinusoid, position 0 -> 1000 mm -> 0 along a random direction, `periods` periods over
//    `frames` frames (each pose is flown out and back in every period, as on the paper's
//    turntable);
//  - each marker measured with Gaussian noise of `noise_mm` at 3 sigma on each axis (the
//    paper's 3 mm, the accuracy of its camera system);
//  - a track of the markers (they keep their names) gives every frame's pose relative to the
//    track's first frame: each frame's markers fitted (VC or least squares) to the track's
//    model of the layout, the markers in the body frame of eqs. 2-9 averaged over every frame
//    of the track (generalised Procrustes; `track_model` off: the first frame's alone), so no
//    error builds up inside a track; consecutive frames are the graph's odometry edges
//    (`--method body`: each frame's own body frame instead, no model);
//  - the track breaks 3 times (`gap` frames unseen): 4 segments, joined by EPnP of the
//    track's model in one camera's image of the next seen frame (3 m away, f = 1000 px, pixel
//    noise equal to the marker noise seen from there), refined by Levenberg-Marquardt;
//    chaining the tracks through these joins is the linear solution (eq. 15);
//  - the pose graph adds loop closures: a frame near (by the linear solution) a frame of an
//    earlier track is registered to it directly (the markers found again by their layout),
//    with a robust loss;
//  - errors are taken after aligning each trial's solution to the truth with one rigid motion
//    (the ATE convention; `align` off: as solved, from the true first pose, when the first
//    frame's own noise turns every pose about it: 0.5 deg at 1 m is 9 mm, so the paper's
//    0.5 deg / 3 mm cannot include that).
#pragma once

#include <random>
#include <vector>

#include "onboard/posegraph/pose_graph.hpp"

namespace stereomap::posegraph {

enum class MarkerMethod { kLeastSquares, kVectorCross, kBodyFrames };

struct GroundTestOptions {
  int frames = 200;
  int periods = 2;  // of the sinusoid: every pose is flown 2 x periods times
  int segments = 4;
  int gap = 3;
  double noise_mm = 3.0;  // 3 sigma, per axis
  double attitude_deg = 30;
  double translation_mm = 1000;
  MarkerMethod method = MarkerMethod::kLeastSquares;
  double loop_radius_mm = 50;  // loop candidates: this close by the linear solution...
  double loop_angle_deg = 10;  // ...and turned by less than this
  bool track_model = true;     // the markers' layout from every frame of a track, not its first
  bool align = true;           // errors after aligning each trial to the truth (ATE convention)
};

// Information matrices of the three kinds of edge, from Monte-Carlo runs of the same
// measurements at the same noise (covariance of the log error, inverted).
struct EdgeInformation {
  Mat6 odometry = Mat6::Identity();
  Mat6 join = Mat6::Identity();
};
EdgeInformation calibrateEdges(const GroundTestOptions& options, std::mt19937& rng);

// Per seen frame, the error of each solution against the truth: attitude as the rotation
// vector of T_true^-1 T_estimate (body axes, degrees), position in world axes (mm), each per
// axis and as a norm.
struct GroundTestErrors {
  struct Axes {
    std::vector<double> deg[3], mm[3], deg_norm, mm_norm;
    void append(const Axes& other);
    double degPerAxis() const;  // the largest per-axis 3 sigma
    double mmPerAxis() const;
  };
  Axes linear, optimised;
  int loop_edges = 0, rejected_edges = 0;
  double solve_ms = 0;
};
GroundTestErrors runGroundTrial(const GroundTestOptions& options,
                                const EdgeInformation& information, std::mt19937& rng);

// The errors of each frame's pose from its own markers and the true layout, least squares:
// what one frame can tell, which no solution that does not model the motion can beat.
GroundTestErrors::Axes oneFrameErrors(const GroundTestOptions& options, std::mt19937& rng);

// 3 x the root mean square of the values (the paper's "3 sigma" of an error).
double threeSigma(const std::vector<double>& values);

}  // namespace stereomap::posegraph
