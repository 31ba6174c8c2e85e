#include "onboard/camera/prefetch_source.hpp"

#include <gtest/gtest.h>

#include <chrono>
#include <thread>

namespace stereomap::camera {
namespace {

using namespace std::chrono_literals;

// Frames 0 .. count-1, each taking `work` to make; its index in the image's first pixel.
class CountingSource : public FrameSource {
 public:
  CountingSource(uint64_t count, std::chrono::milliseconds work) : count_(count), work_(work) {}
  const StereoCamera& camera() const override { return camera_; }
  std::optional<SourceFrame> next() override {
    if (index_ >= count_) return std::nullopt;
    std::this_thread::sleep_for(work_);
    SourceFrame frame;
    frame.index = index_++;
    frame.left = cv::Mat(1, 1, CV_8UC1, cv::Scalar(static_cast<double>(frame.index)));
    return frame;
  }
  std::string describe() const override { return "counting"; }
  bool live() const override { return true; }
  void skip(uint64_t frames) override { index_ += frames; }

 private:
  StereoCamera camera_;
  uint64_t count_;
  std::chrono::milliseconds work_;
  uint64_t index_ = 0;
};

// The indices a source hands out when every third call skips `skipped` frames first.
std::vector<uint64_t> takeAll(FrameSource& source, uint64_t skipped) {
  std::vector<uint64_t> indices;
  for (int call = 0;; ++call) {
    if (call % 3 == 2) source.skip(skipped);
    auto frame = source.next();
    if (!frame) break;
    EXPECT_EQ(frame->left.at<uint8_t>(0, 0), static_cast<uint8_t>(frame->index));
    indices.push_back(frame->index);
  }
  return indices;
}

TEST(PrefetchSource, HandsOutTheInnerSourcesFramesInItsOrderSkipsIncluded) {
  for (const uint64_t skipped : {0, 1, 2, 5}) {
    CountingSource plain(20, 0ms);
    PrefetchSource ahead(std::make_unique<CountingSource>(20, 0ms));
    const auto expected = takeAll(plain, skipped);
    EXPECT_EQ(takeAll(ahead, skipped), expected) << skipped << " skipped";
    EXPECT_FALSE(ahead.next()) << "the end stays the end";
  }
  PrefetchSource ahead(std::make_unique<CountingSource>(3, 0ms));
  EXPECT_TRUE(ahead.live());
  EXPECT_EQ(ahead.describe(), "counting");
  ahead.skip(10);  // past the end
  EXPECT_FALSE(ahead.next());
}

TEST(PrefetchSource, MakesTheNextFrameWhileTheCallerWorks) {
  // 8 frames taking 40 ms each to make, 40 ms of the caller's work on each: about 8 x 40 ms
  // with the making ahead, 8 x 80 ms in turn.
  PrefetchSource ahead(std::make_unique<CountingSource>(8, 40ms));
  const auto start = std::chrono::steady_clock::now();
  while (ahead.next()) std::this_thread::sleep_for(40ms);
  const auto took = std::chrono::steady_clock::now() - start;
  EXPECT_LT(took, 8 * 60ms);
}

}  // namespace
}  // namespace stereomap::camera
