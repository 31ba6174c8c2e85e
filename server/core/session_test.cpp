#include "server/core/session.hpp"

#include <gtest/gtest.h>

#include <chrono>
#include <mutex>
#include <thread>
#include <vector>

#include "testing/synthetic.hpp"

namespace stereomap::core {
namespace {

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

}  // namespace
}  // namespace stereomap::core
