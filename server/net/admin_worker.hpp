// Runs session-management requests (a replay can take seconds) one at a time, off the
// network thread, so that viewers and REST reads never wait for them. At most kMaxWaiting
// wait their turn: a client posting faster than they finish is answered 503 at once
// instead of growing the queue (and the memory it holds) without bound.
#pragma once

#include <boost/asio/post.hpp>
#include <boost/asio/thread_pool.hpp>

#include <atomic>
#include <cstddef>
#include <functional>

namespace stereomap::net {

class AdminWorker {
 public:
  static constexpr size_t kMaxWaiting = 16;
  AdminWorker() = default;
  ~AdminWorker() { stop(); }
  AdminWorker(const AdminWorker&) = delete;
  AdminWorker& operator=(const AdminWorker&) = delete;

  // False (and `job` dropped) when kMaxWaiting jobs are already queued or running, or
  // after stop().
  bool post(std::function<void()> job) {
    if (stopped_) return false;
    if (pending_.fetch_add(1) >= kMaxWaiting) {
      pending_.fetch_sub(1);
      return false;
    }
    boost::asio::post(pool_, [this, job = std::move(job)] {
      job();
      pending_.fetch_sub(1);
    });
    return true;
  }
  // Finishes the job under way; drops the queued ones. Idempotent.
  void stop() {
    stopped_ = true;
    pool_.stop();
    pool_.join();
  }

 private:
  std::atomic<size_t> pending_{0};
  std::atomic<bool> stopped_{false};
  boost::asio::thread_pool pool_{1};
};

}  // namespace stereomap::net
