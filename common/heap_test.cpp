#include "common/heap.hpp"

#include <gtest/gtest.h>

#include <cstring>
#include <memory>

namespace stereomap::common {
namespace {

// Linked with jemalloc as the server is (common/CMakeLists.txt), unless the build has none.
TEST(HeapStats, CountWhatIsLiveAndFollowItsRelease) {
  const auto before = heapStats();
  if (!before) GTEST_SKIP() << "this build does not link jemalloc (STEREOMAP_JEMALLOC=OFF)";
  constexpr size_t kBytes = 64 << 20;
  auto block = std::make_unique<char[]>(kBytes);
  std::memset(block.get(), 1, kBytes);  // touched: in memory
  const auto held = heapStats();
  ASSERT_TRUE(held);
  EXPECT_GE(held->allocated, before->allocated + kBytes);
  EXPECT_GE(held->resident, kBytes);
  block.reset();
  const auto after = heapStats();
  ASSERT_TRUE(after);
  EXPECT_LT(after->allocated, held->allocated - kBytes / 2);
}

// The options of common/jemalloc_options.cpp reach jemalloc (a misspelt or misplaced
// malloc_conf is ignored without a word).
TEST(HeapStats, TheServersJemallocOptionsAreInForce) {
  const auto stats = heapStats();
  if (!stats) GTEST_SKIP() << "this build does not link jemalloc (STEREOMAP_JEMALLOC=OFF)";
  EXPECT_TRUE(stats->background_thread);
}

}  // namespace
}  // namespace stereomap::common
