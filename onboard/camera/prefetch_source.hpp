// A live source whose next frame is made while the vehicle works on the current one, as a
// camera exposes and reads out its next frame on its own hardware while the vehicle's computer
// works. For the simulator: rendering a frame is the sim's cost, not the vehicle's, and taken
// in turn with the vehicle's work it would make a frame's latency (and lateness) the sum of
// both. The frames are the inner source's, in its order, to the bit.
//
//   PrefetchSource source(std::make_unique<sim::SimSource>(options));
//   while (auto frame = source.next()) { ... }  // the following frame renders meanwhile
#pragma once

#include <future>
#include <memory>

#include "onboard/camera/frame_source.hpp"

namespace stereomap::camera {

class PrefetchSource : public FrameSource {
 public:
  explicit PrefetchSource(std::unique_ptr<FrameSource> inner);
  // Waits for a frame still being made (the inner source is not left mid-frame).
  ~PrefetchSource() override;
  PrefetchSource(const PrefetchSource&) = delete;
  PrefetchSource& operator=(const PrefetchSource&) = delete;

  const StereoCamera& camera() const override { return inner_->camera(); }
  // The frame made ahead (waiting for it if it is not done yet); the one after it starts.
  std::optional<SourceFrame> next() override;
  std::string describe() const override { return inner_->describe(); }
  bool live() const override { return inner_->live(); }
  // The frame made ahead counts as the first of those passed over.
  void skip(uint64_t frames) override;

 private:
  std::unique_ptr<FrameSource> inner_;
  // Only this object's calls touch inner_ while a frame is made: describe() and camera() are
  // const reads of what a source fixes when it is made.
  std::future<std::optional<SourceFrame>> ahead_;
  bool ended_ = false;
};

}  // namespace stereomap::camera
