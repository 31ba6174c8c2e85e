#include "common/shutdown.hpp"

#include <gtest/gtest.h>
#include <signal.h>

#include <atomic>

namespace stereomap::common {
namespace {

using namespace std::chrono_literals;

TEST(Shutdown, RequestStopWakesWaitersAndRunsCallbacksOnce) {
  Shutdown shutdown;
  std::atomic<int> calls{0};
  shutdown.onStop([&] { ++calls; });
  EXPECT_FALSE(shutdown.waitFor(10ms));
  std::thread stopper([&] { shutdown.requestStop(); });
  EXPECT_TRUE(shutdown.waitFor(10s));
  stopper.join();
  shutdown.requestStop();
  EXPECT_EQ(calls.load(), 1);
  EXPECT_EQ(shutdown.signal(), 0);
}

TEST(Shutdown, SigtermIsCaughtByTheWatcher) {
  Shutdown shutdown;
  kill(getpid(), SIGTERM);
  EXPECT_TRUE(shutdown.waitFor(10s));
  EXPECT_EQ(shutdown.signal(), SIGTERM);
}

}  // namespace
}  // namespace stereomap::common
