// The pose graph over the odometry's keyframes: the pose-graph paper (section 3 of
// ../shared/PAPERS.md) in the product. Each keyframe becomes a vertex joined to the one before
// by the odometry's relative pose (information from its covariance); a keyframe that starts a
// new track (the odometry was lost) gets only a weak tie to the one before; every keyframe is
// compared with remembered places near its estimate (PlaceMemory), and a verified match
// becomes a loop edge, or the join of the broken track, after which the graph is solved.
// Until a track is joined, its keyframes look for places among every earlier track's, the
// newest too (the place just before the loss is the likeliest to be seen again).
// add() is called from one thread; the getters from any.
//
//   KeyframeGraph graph(camera);
//   for (each VO estimate e with e.keyframe) graph.add(stamp, e.T_world_camera, e.covariance,
//                                                    left, right, /*new_track=*/lost_before);
//   graph.correct(k, T_world_camera_vo)   // any frame, through its keyframe k
#pragma once

#include <mutex>
#include <opencv2/core.hpp>
#include <optional>

#include "onboard/posegraph/place_memory.hpp"
#include "onboard/posegraph/pose_graph.hpp"

namespace stereomap::posegraph {

struct KeyframeGraphOptions {
  PlaceOptions places;
  double search_radius_m = 2.0;   // places searched within this of the estimate...
  double drift_allowance = 0.05;  // ...plus this share of the path flown since the place
  int max_candidates = 4;         // nearest places verified per keyframe
  int recent_keyframes = 20;      // the newest keyframes are the odometry's business
  double min_sigma_rad = 1e-3;    // floors on the odometry edges' standard deviations
  double min_sigma_m = 1e-3;
  double new_track_sigma_rad = 0.5;  // the weak tie across a lost track
  double new_track_sigma_m = 2.0;
  // A correction is reported (and sent to the server, which fuses its map again) only when
  // a keyframe moved by more than this since the last one: a fraction of a map voxel.
  double report_min_change_m = 0.01;
  double report_min_change_rad = 0.002;  // 0.11 deg: 1 cm at 5 m
};

struct KeyframeAdded {
  int keyframe = -1;
  std::optional<PlaceMatch> place;  // the loop closure or join found, if any
  SolveReport solve;                // when the graph was solved
};

class KeyframeGraph {
 public:
  KeyframeGraph(const camera::StereoCamera& camera, const KeyframeGraphOptions& options = {});

  // A keyframe of the odometry: its pose and 6x6 covariance (rotation, translation; world
  // frame, accumulated) as the odometry gives them, and its rectified pair.
  KeyframeAdded add(int64_t stamp_ns, const common::Rigid3& T_world_camera, const Mat6& covariance,
                    const cv::Mat& left, const cv::Mat& right, bool new_track);

  int size() const;
  int loops() const;
  int tracks() const;        // tracks of the odometry so far (1 + losses)
  int joinedTracks() const;  // of those after the first, tied to an earlier one by a place
  // The keyframe's pose after the last solve, and the odometry's own.
  common::Rigid3 optimised(int keyframe) const;
  common::Rigid3 odometry(int keyframe) const;
  // When the keyframe was taken (what a correction sent to the server is keyed by).
  int64_t stamp(int keyframe) const;
  // A pose of the odometry corrected through keyframe `keyframe` (its latest keyframe).
  common::Rigid3 correct(int keyframe, const common::Rigid3& T_world_camera) const;
  // The graph as it stands, for a g2o file (toG2o): vertex k is keyframe k's left camera in
  // the odometry's world frame; odometry, join and loop edges.
  G2oGraph toG2o() const;

 private:
  std::vector<int> candidates(int current) const;

  KeyframeGraphOptions options_;
  PlaceMemory places_;
  mutable std::mutex mutex_;
  PoseGraph graph_;
  std::vector<common::Rigid3> odometry_;
  std::vector<int64_t> stamps_;
  std::vector<Mat6> covariance_;
  std::vector<double> path_m_;  // odometry path length up to each keyframe
  std::vector<int> track_;      // which track (between losses) each keyframe belongs to
  std::vector<bool> joined_;    // per track: tied to an earlier track by a recognised place
  int loops_ = 0;
};

}  // namespace stereomap::posegraph
