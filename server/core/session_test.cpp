#include "server/core/session.hpp"

#include <gtest/gtest.h>

#include <chrono>
#include <mutex>
#include <sstream>
#include <thread>
#include <vector>

#include "testing/synthetic.hpp"

namespace stereomap::core {
namespace {

// Without a journal there is nothing to fuse a frame from later: a full queue drops it.
TEST(Session, AFullQueueDropsAndCountsInsteadOfBlocking) {
  Session session("q", {.resolution = 0.1, .queue_capacity = 1});
  size_t accepted = 0;
  for (int i = 0; i < 20; ++i) {
    FusionJob job{"v",
                  static_cast<uint64_t>(i),
                  0,
                  testing::planeCloud(3.0, 0.5, 0.03),
                  common::Rigid3::identity(),
                  10};
    accepted += session.enqueue(std::move(job));
  }
  session.waitUntilIdle();
  const auto status = session.status();
  EXPECT_EQ(status.frames_received, 20u);
  EXPECT_EQ(status.frames_dropped + status.frames_fused, 20u);
  EXPECT_EQ(status.frames_fused, accepted);
  EXPECT_GT(status.frames_dropped, 0u);
  EXPECT_EQ(status.frames_deferred, 0u);
}

// Frames keep coming, faster than a correction's re-fusion reads the journal, so that it
// never catches up by reading and hands over with frames only the worker's tail holds: the
// swapped-in map has every frame, each where the correction puts it. The journal is a list
// of the jobs (the store's reading is tested with the store).
TEST(Session, FramesArrivingDuringARefusionAreNotLost) {
  std::vector<FusionJob> journal;  // what the session was sent, numbered 1..
  std::mutex journal_mutex;
  auto job = [](int i, double dy) {
    common::Rigid3 pose;
    pose.translation = {0, dy, 0.1 * i};  // each frame a wall patch of its own
    return FusionJob{
        "v", static_cast<uint64_t>(i),    1000 + i, testing::planeCloud(2.0, 0.4, 0.05), pose,
        10,  static_cast<uint64_t>(i + 1)};
  };
  Session::Options options{.resolution = 0.1};
  options.reread_frames = [&](uint64_t after, uint64_t up_to,
                              const std::function<void(FusionJob &&)>& fuse) {
    for (size_t i = 0;; ++i) {
      FusionJob copy;
      {
        std::lock_guard lock(journal_mutex);
        if (i >= journal.size()) break;
        copy = journal[i];
      }
      if (copy.journal_number <= after || copy.journal_number > up_to) continue;
      std::this_thread::sleep_for(std::chrono::milliseconds(5));  // slower than frames come
      fuse(std::move(copy));
    }
    return common::Status(common::Ok{});
  };
  Session session("r", options);
  int sent = 0;
  auto send = [&] {
    auto frame = job(sent++, 0.5);  // 0.5 m off in y
    session.addPose({"v", frame.stamp_ns, frame.T_map_camera});
    {
      std::lock_guard lock(journal_mutex);
      journal.push_back(frame);
    }
    // Waits for room: a full queue drops frames by design (another test), and a slow build
    // (AddressSanitizer) filled it here before the re-fusion ended.
    ASSERT_TRUE(session.enqueue(std::move(frame), /*wait_for_room=*/true));
  };
  for (int i = 0; i < 20; ++i) send();
  session.waitUntilIdle();
  std::vector<StampedBodyPose> keyframes;
  for (int i = 0; i < 20; i += 5) keyframes.push_back({job(i, 0).stamp_ns, job(i, 0).T_map_camera});
  auto correction = session.correctionFor("v", keyframes);
  ASSERT_TRUE(correction);
  session.correct("v", *correction, /*refuse=*/true);
  while (session.status().refusions == 0 && sent < 2000) {
    send();
    std::this_thread::sleep_for(std::chrono::milliseconds(3));
  }
  for (int i = 0; i < 5; ++i) send();
  session.waitUntilIdle();
  EXPECT_EQ(session.status().refusions, 1u);
  EXPECT_EQ(session.status().frames_fused, static_cast<uint64_t>(sent));

  Session right("t", {.resolution = 0.1});
  for (int i = 0; i < sent; ++i) ASSERT_TRUE(right.enqueue(job(i, 0), /*wait_for_room=*/true));
  right.waitUntilIdle();
  EXPECT_EQ(session.occupiedVoxels(), right.occupiedVoxels());
}

// With a journal, a full queue defers frames instead of dropping them: once the queue has
// drained they are read from the journal and fused, so the map ends with every frame. No
// snapshot is taken while one is deferred: it would claim to hold it, and recovery would then
// never fuse it. Frames 1 and 2 are large (slow to fuse), far from the rest; frame 3 finds the
// queue full; frame 4 is queued while 2 is being fused, so it is fused before 3 is: a snapshot
// then would be labelled 4 without holding 3. Each frame is a patch of its own, so the order
// of fusion does not change the map.
TEST(Session, AFullQueueDefersFramesAndFusesThemFromTheJournal) {
  auto job = [](int number) {
    const bool large = number <= 2;
    common::Rigid3 pose;
    pose.translation = {0, large ? 10.0 : 0.0, 0.3 * number};
    return FusionJob{"v",
                     static_cast<uint64_t>(number),
                     1000 + number,
                     testing::planeCloud(2.0, large ? 1.0 : 0.04, large ? 0.002 : 0.02),
                     pose,
                     10,
                     static_cast<uint64_t>(number)};
  };
  constexpr int kFrames = 30;
  std::vector<FusionJob> journal;
  for (int i = 1; i <= kFrames; ++i) journal.push_back(job(i));
  Session::Options options{.resolution = 0.1, .queue_capacity = 1, .snapshot_every = 1};
  options.reread_frames = [&](uint64_t after, uint64_t up_to,
                              const std::function<void(FusionJob &&)>& fuse) {
    for (const auto& frame : journal) {
      if (frame.journal_number > after && frame.journal_number <= up_to) fuse(FusionJob(frame));
    }
    return common::Status(common::Ok{});
  };
  // Every snapshot must hold every frame numbered up to its label.
  std::mutex snapshots_mutex;
  std::vector<std::pair<uint64_t, size_t>> snapshots;  // label, frames missing from it
  options.on_snapshot = [&](uint64_t label, const std::string& ot) {
    std::istringstream in(ot);
    auto map = fusion::OccupancyMap::load(in);
    size_t missing = 0;
    for (const auto& frame : journal) {
      if (frame.journal_number > label || !map) continue;
      missing += (*map)->query(frame.T_map_camera * common::Vec3(2.0, 0, 0)) !=
                 fusion::Occupancy::kOccupied;
    }
    std::lock_guard lock(snapshots_mutex);
    snapshots.emplace_back(label, map ? missing : journal.size());
    return common::Status(common::Ok{});
  };
  Session session("d", options);
  auto backlogReaches = [&](size_t backlog) {
    for (int i = 0; i < 20000 && session.status().backlog != backlog; ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    return session.status().backlog == backlog;
  };
  ASSERT_TRUE(session.enqueue(job(1)));
  std::this_thread::sleep_for(
      std::chrono::milliseconds(20));    // taken (1 M points: it fuses longer)
  ASSERT_TRUE(session.enqueue(job(2)));  // queued while 1 is fused
  ASSERT_TRUE(session.enqueue(job(3)));  // the queue is full: deferred
  ASSERT_EQ(session.status().frames_deferred, 1u) << "frame 1 fused in under 20 ms";
  // 2 taken (the queue empty, 3 deferred, the worker busy): the rest is queued behind it.
  ASSERT_TRUE(backlogReaches(2));
  for (int i = 4; i <= kFrames; ++i) EXPECT_TRUE(session.enqueue(job(i)));
  session.waitUntilIdle();
  const auto status = session.status();
  EXPECT_GE(status.frames_deferred, 1u);
  EXPECT_EQ(status.frames_dropped, 0u);
  EXPECT_EQ(status.frames_fused, static_cast<uint64_t>(kFrames));
  EXPECT_EQ(status.backlog, 0u);

  Session reference("r", {.resolution = 0.1});
  for (const auto& frame : journal) {
    ASSERT_TRUE(reference.enqueue(FusionJob(frame), /*wait_for_room=*/true));
  }
  reference.waitUntilIdle();
  EXPECT_EQ(session.occupiedVoxels(), reference.occupiedVoxels());
  std::lock_guard lock(snapshots_mutex);
  EXPECT_FALSE(snapshots.empty());
  for (const auto& [label, missing] : snapshots) EXPECT_EQ(missing, 0u) << "snapshot " << label;
}

}  // namespace
}  // namespace stereomap::core

namespace stereomap::core {
namespace {

// A vehicle in its own frame (holdApart): its frames stay out of the session's map, in a map
// of their own, until join(); then a re-fusion puts them where its alignment says, and the map
// is the one a vehicle in the session's frame would have made with the same frames.
TEST(Session, AVehicleInItsOwnFrameIsHeldApartUntilItJoins) {
  std::vector<FusionJob> journal;
  std::mutex journal_mutex;
  // T_session_own: where vehicle b's frame lies in the session's.
  const common::Rigid3 T{common::Quat(Eigen::AngleAxisd(2.0, common::Vec3::UnitZ())),
                         common::Vec3(4.0, -3.0, 0.5)};
  auto frame = [&](const std::string& vehicle, int i, const common::Rigid3& T_frame_session) {
    common::Rigid3 pose;
    pose.translation = {0.3 * i, 0.5, 0.1 * i};
    return FusionJob{vehicle,
                     static_cast<uint64_t>(i),
                     1000 + i,
                     testing::planeCloud(2.0, 0.4, 0.05),
                     T_frame_session * pose,
                     10,
                     0};
  };
  Session::Options options{.resolution = 0.1};
  options.reread_frames = [&](uint64_t after, uint64_t up_to,
                              const std::function<void(FusionJob &&)>& fuse) {
    std::lock_guard lock(journal_mutex);
    for (const auto& job : journal) {
      if (job.journal_number > after && job.journal_number <= up_to) fuse(FusionJob(job));
    }
    return common::Status(common::Ok{});
  };
  Session session("own", options);
  Session reference("ref", {.resolution = 0.1});  // every frame sent in the session's frame
  auto send = [&](FusionJob job, const common::Rigid3& T_session_frame) {
    {
      std::lock_guard lock(journal_mutex);
      job.journal_number = journal.size() + 1;
      journal.push_back(job);
    }
    session.addPose({job.vehicle_id, job.stamp_ns, job.T_map_camera});
    FusionJob placed = job;
    placed.T_map_camera = T_session_frame * job.T_map_camera;
    ASSERT_TRUE(reference.enqueue(std::move(placed), true));
    ASSERT_TRUE(session.enqueue(std::move(job), true));
  };
  EXPECT_TRUE(Session("empty", {.resolution = 0.1}).holdApart("first", true))
      << "the first vehicle of an empty session is its reference";
  for (int i = 0; i < 5; ++i) send(frame("a", i, common::Rigid3::identity()), {});
  session.waitUntilIdle();
  const auto only_a = session.occupiedVoxels();
  EXPECT_FALSE(session.holdApart("b", true)) << "a's frames are in the map: b is not the reference";
  for (int i = 0; i < 5; ++i) send(frame("b", i, T.inverse()), T);
  session.waitUntilIdle();
  EXPECT_EQ(session.occupiedVoxels(), only_a) << "b's frames were fused before it joined";
  ASSERT_NE(session.heldMap("b"), nullptr);
  EXPECT_GT(session.heldMap("b")->occupiedCount(), 100u);
  EXPECT_EQ(session.frameState("b", nullptr), proto::FrameState::kAligning);
  EXPECT_EQ(session.status().vehicle_frames.at(0).held_frames, 5u);
  EXPECT_TRUE(session.trajectory().back().held) << "b's poses are in its own frame";
  EXPECT_FALSE(session.trajectory().front().held);

  // Two attempts must agree before a join (the caller's rule, kept by the session).
  EXPECT_FALSE(session.noteAttempt("b", T, "", 0.1, 0.5).agrees);
  EXPECT_FALSE(session.noteAttempt("b", std::nullopt, "too little overlap", 0.1, 0.5).agrees);
  EXPECT_FALSE(session.noteAttempt("b", T, "", 0.1, 0.5).agrees);
  const auto agreed = session.noteAttempt("b", T, "", 0.1, 0.5);
  EXPECT_TRUE(agreed.agrees);
  EXPECT_EQ(agreed.attempts, 4u);

  session.join("b", T, 0.9, 0.03, /*refuse=*/true);
  send(frame("b", 5, T.inverse()), T);  // after the join: placed at once
  session.waitUntilIdle();
  reference.waitUntilIdle();
  EXPECT_EQ(session.occupiedVoxels(), reference.occupiedVoxels());
  common::Rigid3 told;
  EXPECT_EQ(session.frameState("b", &told), proto::FrameState::kAligned);
  EXPECT_LT((told.translation - T.translation).norm(), 1e-12);
  EXPECT_EQ(session.heldMap("b"), nullptr);
  const auto poses = session.trajectory();
  EXPECT_FALSE(poses.back().held);
  const common::Vec3 in_session =
      frame("b", 5, common::Rigid3::identity()).T_map_camera.translation;
  EXPECT_LT((poses.back().T_map_body.translation - in_session).norm(), 1e-9);
  EXPECT_EQ(session.status().refusions, 1u);
}

}  // namespace
}  // namespace stereomap::core
