// Follows the odometry frame by frame with a KeyframeGraph: picks the frames that enter the
// graph (the odometry's keyframes, and the first tracked frame after a loss, which starts a
// new track), hands them to the graph (on a worker thread when `background`, so that
// place recognition and solving never stall tracking), and corrects poses with it:
//  - now(): a frame's pose through the newest keyframe the graph has taken (what a vehicle
//    publishes live);
//  - finish(): every frame's pose through the final graph, frames the odometry lost
//    interpolated between the tracked frames on either side (the corrected trajectory);
//  - takeCorrection(): after a solve that found a place (a loop closure or the join of a
//    lost track), every keyframe's new pose: what the vehicle sends the server, which fuses
//    its map again with them.
#pragma once

#include <condition_variable>
#include <deque>
#include <memory>
#include <thread>

#include "onboard/posegraph/keyframe_graph.hpp"

namespace stereomap::posegraph {

struct FollowedFrame {
  int64_t stamp_ns = 0;
  common::Rigid3 T_world_camera;  // the odometry's
  Mat6 covariance = Mat6::Zero();
  bool keyframe = false;  // the odometry made one here
  bool lost = false;      // the odometry lost track here
  cv::Mat left, right;    // rectified; only read when the frame enters the graph
};

// A keyframe's pose after a solve, keyed by the stamp of the frame it was taken at.
struct KeyframePose {
  int64_t stamp_ns = 0;
  common::Rigid3 T_world_camera;
};

struct FollowerStats {
  int keyframes = 0, loops = 0, tracks = 0, joined_tracks = 0;
  double solve_ms_max = 0;
};

class GraphFollower {
 public:
  GraphFollower(const camera::StereoCamera& camera, const KeyframeGraphOptions& options,
                bool background);
  ~GraphFollower();
  GraphFollower(const GraphFollower&) = delete;
  GraphFollower& operator=(const GraphFollower&) = delete;

  // One frame, in order; returns its pose corrected by the graph as it stands.
  common::Rigid3 follow(const FollowedFrame& frame);
  std::vector<common::Rigid3> finish();
  // The keyframe graph for a g2o file (KeyframeGraph::toG2o), as it stands.
  G2oGraph keyframeGraph() const { return graph_.toG2o(); }
  // Every keyframe's pose after the newest solve that found a place and moved some keyframe
  // by more than the options' report_min_change since the poses last reported; empty when
  // there was none since the last call.
  std::vector<KeyframePose> takeCorrection();
  // Blocks until the graph has taken every keyframe handed to it so far.
  void waitUntilCaughtUp();
  FollowerStats stats() const;

 private:
  struct Pending {
    int keyframe;
    FollowedFrame frame;
    bool new_track;
  };
  void work();
  void process(const Pending& pending);

  KeyframeGraph graph_;
  const bool background_;
  // Per frame: the keyframe it is corrected through (-1: none yet), its odometry pose, lost.
  std::vector<int> through_;
  std::vector<common::Rigid3> odometry_;
  std::vector<bool> lost_;
  std::vector<int64_t> stamps_;
  int submitted_ = 0;
  bool lost_since_keyframe_ = false;

  mutable std::mutex mutex_;
  std::condition_variable changed_;
  std::deque<Pending> queue_;
  int processed_ = 0;  // keyframes the graph has taken
  // opt(k) * odometry(k)^-1 of the newest taken keyframe: follow() reads only this, so that
  // a solve under way never holds up tracking.
  common::Rigid3 correction_;
  std::vector<KeyframePose> new_poses_;  // for takeCorrection()
  std::vector<KeyframePose> reported_;   // the poses last handed to takeCorrection()
  const double min_change_m_, min_change_rad_;
  bool movedEnough(const std::vector<KeyframePose>& moved) const;
  bool stopping_ = false;
  double solve_ms_max_ = 0;
  std::thread worker_;
};

}  // namespace stereomap::posegraph
