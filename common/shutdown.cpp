#include "common/shutdown.hpp"

#include <pthread.h>
#include <signal.h>

namespace stereomap::common {

namespace {
sigset_t stopSignals() {
  sigset_t set;
  sigemptyset(&set);
  sigaddset(&set, SIGINT);
  sigaddset(&set, SIGTERM);
  return set;
}
}  // namespace

Shutdown::Shutdown() {
  const sigset_t set = stopSignals();
  pthread_sigmask(SIG_BLOCK, &set, nullptr);  // inherited by every thread started later
  watcher_ = std::thread([this, set] {
    int received = 0;
    if (sigwait(&set, &received) != 0) return;
    {
      std::lock_guard lock(mutex_);
      if (closing_) return;  // woken by the destructor, not by a real signal
    }
    stopWith(received);
  });
}

Shutdown::~Shutdown() {
  {
    std::lock_guard lock(mutex_);
    closing_ = true;
  }
  // Wake the watcher's sigwait with a signal aimed at it alone (every thread blocks SIGTERM,
  // so it kills nothing: the watcher takes it from sigwait and sees closing_).
  pthread_kill(watcher_.native_handle(), SIGTERM);  // NOLINT(bugprone-bad-signal-to-kill-thread)
  watcher_.join();
}

void Shutdown::stopWith(int signal) {
  std::vector<std::function<void()>> callbacks;
  {
    std::lock_guard lock(mutex_);
    stop_ = true;
    if (signal_ == 0) signal_ = signal;
    callbacks.swap(callbacks_);  // each callback runs once
  }
  changed_.notify_all();
  for (auto& callback : callbacks) callback();
}

void Shutdown::requestStop() { stopWith(0); }

bool Shutdown::stopRequested() const {
  std::lock_guard lock(mutex_);
  return stop_;
}

bool Shutdown::waitFor(std::chrono::nanoseconds timeout) const {
  std::unique_lock lock(mutex_);
  return changed_.wait_for(lock, timeout, [this] { return stop_; });
}

void Shutdown::wait() const {
  std::unique_lock lock(mutex_);
  changed_.wait(lock, [this] { return stop_; });
}

void Shutdown::onStop(std::function<void()> callback) {
  {
    std::lock_guard lock(mutex_);
    if (!stop_) {
      callbacks_.push_back(std::move(callback));
      return;
    }
  }
  callback();  // already stopping: now, outside the lock
}

int Shutdown::signal() const {
  std::lock_guard lock(mutex_);
  return signal_;
}

}  // namespace stereomap::common
