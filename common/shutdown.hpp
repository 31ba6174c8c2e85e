// A stop request for a process: SIGINT/SIGTERM (or requestStop()) wakes every waiter at
// once, so loops wait on it instead of sleep-polling. Construct it first in main(), before
// other threads start: it blocks those signals so that only its own thread receives them.
#pragma once

#include <chrono>
#include <condition_variable>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

namespace stereomap::common {

class Shutdown {
 public:
  Shutdown();
  ~Shutdown();
  Shutdown(const Shutdown&) = delete;
  Shutdown& operator=(const Shutdown&) = delete;

  void requestStop();
  bool stopRequested() const;
  // Waits up to `timeout`; true when a stop was requested (possibly earlier).
  bool waitFor(std::chrono::nanoseconds timeout) const;
  void wait() const;
  // Called once, on the signal thread (or the requesting thread), when a stop is requested.
  void onStop(std::function<void()> callback);
  // The signal that caused the stop (0 if requested by code or not stopped).
  int signal() const;

 private:
  mutable std::mutex mutex_;
  mutable std::condition_variable changed_;
  bool stop_ = false;
  bool closing_ = false;
  int signal_ = 0;
  std::vector<std::function<void()>> callbacks_;
  std::thread watcher_;
  void stopWith(int signal);
};

}  // namespace stereomap::common
