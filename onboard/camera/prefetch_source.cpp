#include "onboard/camera/prefetch_source.hpp"

#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

namespace stereomap::camera {

namespace {
constexpr int kAheadNice = 10;  // of 19; the vehicle's threads run at 0
}  // namespace

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
  ahead_ = std::async(std::launch::async, [this] {
    // A camera's hardware is not the vehicle's computer: the frame made ahead takes the CPU the
    // vehicle's work leaves (on two cores, at its priority it took the vehicle's main thread
    // from its own frames: the landing watch's 13 ms ran 25-50 ms). Lower priority, not less
    // work: a render that cannot keep up still shows as the vehicle waiting, then late frames.
    setpriority(PRIO_PROCESS, static_cast<id_t>(syscall(SYS_gettid)), kAheadNice);
    return inner_->next();
  });
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
