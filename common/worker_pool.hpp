// Threads that live with the process for the parallel halves of per-frame work (fusion's ray
// casting and tree update), so that no thread is created per frame and several sessions
// fusing at once share the cores instead of each spawning helpers.
//
//   WorkerPool pool(1);
//   pool.runPair([&] { castRays(0, half); }, [&] { castRays(half, n); });
#pragma once

#include <condition_variable>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

namespace stereomap::common {

// Lowers the calling thread's scheduling priority (nice +10) for work that can wait: fusion
// has a queue (and, with a journal, frames deferred to it), while the ingest path's journal
// commits and acknowledgements are what vehicles wait on. On a busy machine the kernel then
// runs those first (measured: a cluster server's commit p99, docs/BENCHMARKS.md). Lowering
// needs no privilege; a failure is ignored (the thread runs at normal priority).
void runAsBackgroundWork();

class WorkerPool {
 public:
  // `threads` helpers (at least one); `background`: they run as background work
  // (runAsBackgroundWork).
  explicit WorkerPool(unsigned threads, bool background = false);
  ~WorkerPool();  // finishes the tasks under way
  WorkerPool(const WorkerPool&) = delete;
  WorkerPool& operator=(const WorkerPool&) = delete;

  // Runs `first` on the calling thread and `second` on a helper; returns when both are done.
  // When no helper has taken `second` by the time `first` is done (every helper busy with
  // other sessions' work), the caller runs it itself: it never waits for a free thread.
  // Exceptions must not escape either function.
  void runPair(const std::function<void()>& first, const std::function<void()>& second);

  unsigned threads() const { return static_cast<unsigned>(threads_.size()); }

 private:
  struct Task;
  void run();

  std::mutex mutex_;
  std::condition_variable changed_;
  std::deque<std::shared_ptr<Task>> tasks_;
  bool stopping_ = false;
  std::vector<std::thread> threads_;
};

}  // namespace stereomap::common
