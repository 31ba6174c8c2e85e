#include "common/worker_pool.hpp"

#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <atomic>

namespace stereomap::common {

void runAsBackgroundWork() {
  // On Linux a nice value is per thread: PRIO_PROCESS with the thread's id.
  const auto tid = static_cast<id_t>(::syscall(SYS_gettid));
  (void)::setpriority(PRIO_PROCESS, tid, 10);
}

// Who runs a task is decided once: a helper or the caller takes it from kWaiting.
struct WorkerPool::Task {
  enum State { kWaiting, kTaken, kDone };
  explicit Task(const std::function<void()>& work) : work(work) {}
  const std::function<void()>& work;  // lives on the caller's stack until kDone
  std::atomic<int> state{kWaiting};
  std::mutex mutex;
  std::condition_variable done;

  bool take() {
    int expected = kWaiting;
    return state.compare_exchange_strong(expected, kTaken);
  }
  void finish() {
    {
      std::lock_guard lock(mutex);
      state = kDone;
    }
    done.notify_all();
  }
};

WorkerPool::WorkerPool(unsigned threads, bool background) {
  for (unsigned i = 0; i < std::max(threads, 1u); ++i) {
    threads_.emplace_back([this, background] {
      if (background) runAsBackgroundWork();
      run();
    });
  }
}

WorkerPool::~WorkerPool() {
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
  }
  changed_.notify_all();
  for (auto& thread : threads_) thread.join();
}

void WorkerPool::runPair(const std::function<void()>& first, const std::function<void()>& second) {
  auto task = std::make_shared<Task>(second);
  {
    std::lock_guard lock(mutex_);
    tasks_.push_back(task);
  }
  changed_.notify_one();
  first();
  if (task->take()) {  // no helper got to it: do it here rather than wait
    second();
    task->state = Task::kDone;
    return;
  }
  std::unique_lock lock(task->mutex);
  task->done.wait(lock, [&] { return task->state == Task::kDone; });
}

void WorkerPool::run() {
  for (;;) {
    std::shared_ptr<Task> task;
    {
      std::unique_lock lock(mutex_);
      changed_.wait(lock, [this] { return stopping_ || !tasks_.empty(); });
      if (tasks_.empty()) return;  // stopping
      task = std::move(tasks_.front());
      tasks_.pop_front();
    }
    // A task its caller took back is left alone (its work may already be gone).
    if (!task->take()) continue;
    task->work();
    task->finish();
  }
}

}  // namespace stereomap::common
