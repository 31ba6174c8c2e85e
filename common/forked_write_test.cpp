#include "common/forked_write.hpp"

#include <gtest/gtest.h>

#include <ostream>
#include <thread>
#include <vector>

#include "common/worker_pool.hpp"

namespace stereomap::common {
namespace {

TEST(ForkedWrite, CollectsWhatTheChildWroteAsOfTheFork) {
  std::vector<char> data(4 << 20, 'a');  // larger than a pipe's buffer
  auto job = ForkedWrite::start([&](std::ostream& out) {
    out.write(data.data(), static_cast<std::streamsize>(data.size()));
    return true;
  });
  ASSERT_TRUE(job) << job.error().message;
  std::fill(data.begin(), data.end(), 'b');  // after the fork: the child keeps its copy
  auto bytes = job->finish();
  ASSERT_TRUE(bytes) << bytes.error().message;
  EXPECT_EQ(*bytes, std::string(4 << 20, 'a'));
}

TEST(ForkedWrite, AFailedWriteIsAnError) {
  auto job = ForkedWrite::start([](std::ostream& out) {
    out << "partial";
    return false;
  });
  ASSERT_TRUE(job);
  auto bytes = job->finish();
  ASSERT_FALSE(bytes);
  EXPECT_NE(bytes.error().message.find("failed"), std::string::npos);
}

TEST(ForkedWrite, AChildPastItsDeadlineIsKilledAndAnError) {
  auto job = ForkedWrite::start([](std::ostream& out) {
    out << "started";
    out.flush();
    for (;;) std::this_thread::sleep_for(std::chrono::seconds(1));  // a parser that loops
    return true;
  });
  ASSERT_TRUE(job);
  const auto started = std::chrono::steady_clock::now();
  auto bytes = job->finish(std::chrono::milliseconds(300));
  const auto took = std::chrono::steady_clock::now() - started;
  ASSERT_FALSE(bytes);
  EXPECT_EQ(bytes.error().code, ErrorCode::kUnavailable);
  EXPECT_NE(bytes.error().message.find("within 300 ms"), std::string::npos);
  EXPECT_GE(took, std::chrono::milliseconds(300));
  EXPECT_LT(took, std::chrono::seconds(5));
  // A child done in time is collected as without a deadline.
  auto quick = ForkedWrite::start([](std::ostream& out) { return static_cast<bool>(out << "ok"); });
  ASSERT_TRUE(quick);
  auto done = quick->finish(std::chrono::seconds(30));
  ASSERT_TRUE(done) << done.error().message;
  EXPECT_EQ(*done, "ok");
}

TEST(ForkedWrite, AnUncollectedChildIsKilledAndReaped) {
  auto job = ForkedWrite::start([](std::ostream& out) {
    for (;;) out << std::string(1 << 16, 'x');  // blocks on the full pipe
    return true;
  });
  ASSERT_TRUE(job);
  { auto abandoned = std::move(*job); }  // must return, not hang
  SUCCEED();
}

TEST(WorkerPool, RunsBothHalvesEvenWhenItsThreadsAreBusy) {
  WorkerPool pool(1);
  std::atomic<int> done{0};
  std::vector<std::thread> callers;
  for (int c = 0; c < 4; ++c) {
    callers.emplace_back([&] {
      for (int i = 0; i < 200; ++i) {
        int first = 0, second = 0;
        pool.runPair([&] { first = 1; }, [&] { second = 1; });
        ASSERT_EQ(first + second, 2);
        ++done;
      }
    });
  }
  for (auto& caller : callers) caller.join();
  EXPECT_EQ(done, 800);
}

}  // namespace
}  // namespace stereomap::common
