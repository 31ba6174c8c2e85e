#include "onboard/camera/prefetch_source.hpp"

namespace stereomap::camera {

PrefetchSource::PrefetchSource(std::unique_ptr<FrameSource> inner) : inner_(std::move(inner)) {}

PrefetchSource::~PrefetchSource() {
  if (ahead_.valid()) ahead_.wait();
}

std::optional<SourceFrame> PrefetchSource::next() {
  if (ended_) return std::nullopt;
  // The first frame is made now: a source's clock starts with the first frame taken.
  std::optional<SourceFrame> frame = ahead_.valid() ? ahead_.get() : inner_->next();
  if (!frame) {
    ended_ = true;
    return std::nullopt;
  }
  ahead_ = std::async(std::launch::async, [this] { return inner_->next(); });
  return frame;
}

void PrefetchSource::skip(uint64_t frames) {
  if (frames == 0 || ended_) return;
  if (ahead_.valid()) {
    if (!ahead_.get()) {
      ended_ = true;
      return;
    }
    --frames;
  }
  inner_->skip(frames);
}

}  // namespace stereomap::camera
