// One background thread that runs jobs one at a time where only the newest job of each key is
// wanted (a viewer's newest replay, a session's newest 2D grid): a job posted while an older
// one of its key waits replaces it. Results are taken by whoever polls.
//
//   KeyedWorker<uint64_t, Grid> worker;
//   worker.post(session, [=] { return makeGrid(session); });
//   for (auto& [key, grid] : worker.take()) ...
#pragma once

#include <condition_variable>
#include <functional>
#include <map>
#include <mutex>
#include <thread>
#include <utility>
#include <vector>

namespace stereomap::common {

template <typename Key, typename Result>
class KeyedWorker {
 public:
  KeyedWorker() = default;
  ~KeyedWorker() {  // the job under way finishes; waiting ones are dropped
    {
      std::lock_guard lock(mutex_);
      stopping_ = true;
    }
    changed_.notify_one();
    if (thread_.joinable()) thread_.join();
  }
  KeyedWorker(const KeyedWorker&) = delete;
  KeyedWorker& operator=(const KeyedWorker&) = delete;

  void post(const Key& key, std::function<Result()> job) {
    std::lock_guard lock(mutex_);
    jobs_[key] = std::move(job);
    if (!thread_.joinable()) thread_ = std::thread([this] { run(); });  // started when needed
    changed_.notify_one();
  }
  // Whether a job of `key` waits or runs.
  bool busy(const Key& key) const {
    std::lock_guard lock(mutex_);
    return jobs_.count(key) > 0 || (running_ && running_key_ == key);
  }
  std::vector<std::pair<Key, Result>> take() {
    std::lock_guard lock(mutex_);
    return std::exchange(done_, {});
  }

 private:
  void run() {
    for (;;) {
      std::function<Result()> job;
      {
        std::unique_lock lock(mutex_);
        changed_.wait(lock, [this] { return stopping_ || !jobs_.empty(); });
        if (stopping_) return;
        running_key_ = jobs_.begin()->first;
        running_ = true;
        job = std::move(jobs_.begin()->second);
        jobs_.erase(jobs_.begin());
      }
      Result result = job();
      std::lock_guard lock(mutex_);
      running_ = false;
      done_.emplace_back(running_key_, std::move(result));
    }
  }

  mutable std::mutex mutex_;
  std::condition_variable changed_;
  std::map<Key, std::function<Result()>> jobs_;
  std::vector<std::pair<Key, Result>> done_;
  Key running_key_{};
  bool running_ = false, stopping_ = false;
  std::thread thread_;
};

}  // namespace stereomap::common
