// The admin requests' worker: one job at a time, a bounded queue, queued jobs dropped at stop.
#include "server/net/admin_worker.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <future>
#include <thread>

namespace stereomap::net {
namespace {

TEST(AdminWorker, RunsJobsInTurnAndRefusesBeyondItsQueue) {
  AdminWorker worker;
  std::promise<void> release;
  std::shared_future<void> released = release.get_future().share();
  std::atomic<int> ran{0}, running{0}, most_at_once{0};
  auto job = [&] {
    most_at_once = std::max(most_at_once.load(), ++running);
    released.wait();
    --running;
    ++ran;
  };
  for (size_t i = 0; i < AdminWorker::kMaxWaiting; ++i) EXPECT_TRUE(worker.post(job)) << i;
  EXPECT_FALSE(worker.post(job));  // the 17th: refused, not queued
  while (running.load() == 0) std::this_thread::yield();
  release.set_value();
  worker.stop();  // finishes the job under way, drops the rest
  EXPECT_GE(ran.load(), 1);
  EXPECT_EQ(most_at_once.load(), 1);
  EXPECT_FALSE(worker.post(job));  // stopped
}

TEST(AdminWorker, TakesJobsAgainOnceTheQueueDrains) {
  AdminWorker worker;
  std::atomic<int> ran{0};
  for (int round = 0; round < 3; ++round) {
    std::promise<void> done;
    // (One place spare: the last round's final job counts until it has returned.)
    for (size_t i = 0; i + 2 < AdminWorker::kMaxWaiting; ++i) {
      ASSERT_TRUE(worker.post([&] { ++ran; }));
    }
    ASSERT_TRUE(worker.post([&] { done.set_value(); }));
    done.get_future().wait();
  }
  EXPECT_EQ(ran.load(), 3 * static_cast<int>(AdminWorker::kMaxWaiting - 2));
}

}  // namespace
}  // namespace stereomap::net
