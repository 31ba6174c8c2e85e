// A frame source that goes dark: frames [first, first + count) of the wrapped source come out
// black (both images), as when a camera is covered or blinded; everything else passes
// through. Used to force the odometry to lose track.
#pragma once

#include <memory>

#include "onboard/camera/frame_source.hpp"

namespace stereomap::testing {

class BlackoutSource : public camera::FrameSource {
 public:
  BlackoutSource(std::unique_ptr<camera::FrameSource> inner, uint64_t first, uint64_t count)
      : inner_(std::move(inner)), first_(first), count_(count) {}

  const camera::StereoCamera& camera() const override { return inner_->camera(); }
  std::optional<camera::SourceFrame> next() override {
    auto frame = inner_->next();
    if (frame && index_ >= first_ && index_ < first_ + count_) {
      frame->left.setTo(0);
      frame->right.setTo(0);
    }
    ++index_;
    return frame;
  }
  std::string describe() const override { return inner_->describe() + " with a blackout"; }

 private:
  std::unique_ptr<camera::FrameSource> inner_;
  uint64_t first_, count_, index_ = 0;
};

}  // namespace stereomap::testing
