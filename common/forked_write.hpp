// Serialises a large in-memory structure without stopping the thread that owns it: fork()
// gives a child process a frozen, copy-on-write image of the parent, the child writes the
// bytes into a pipe and exits, and the parent collects them on any thread. The owner is held
// up only for the fork itself (page tables are copied, not the data), which is why the
// server's snapshots and map exports never stall fusion for a whole serialisation.
//
//   std::optional<ForkedWrite> job;
//   { std::lock_guard lock(map_mutex); job.emplace(ForkedWrite::start([&](std::ostream& out) {
//       return map.writeFull(out); }).value()); }   // the lock only covers the fork
//   Result<std::string> bytes = job->finish();        // later, without the lock
//
// The child runs only `write` (no locks, no logging, no threads) and ends with _exit; it dies
// with the parent. glibc's fork keeps malloc usable in the child.
#pragma once

#include <sys/types.h>

#include <chrono>
#include <functional>
#include <iosfwd>
#include <optional>
#include <string>

#include "common/result.hpp"

namespace stereomap::common {

class ForkedWrite {
 public:
  // Forks now; the child calls write(out) and exits 0 when it returned true. Call with the
  // data consistent (its lock held). kUnavailable when pipe() or fork() fails.
  static Result<ForkedWrite> start(const std::function<bool(std::ostream&)>& write);

  ForkedWrite(ForkedWrite&& other) noexcept;
  ForkedWrite& operator=(ForkedWrite&& other) noexcept;
  ForkedWrite(const ForkedWrite&) = delete;
  ForkedWrite& operator=(const ForkedWrite&) = delete;
  ~ForkedWrite();  // a child not collected is killed and reaped

  // Blocks until the child is done: everything it wrote, or an error when it failed. With a
  // deadline, a child not done by then is killed and the answer is kUnavailable.
  Result<std::string> finish(std::optional<std::chrono::milliseconds> deadline = std::nullopt);

 private:
  ForkedWrite(pid_t child, int read_fd) : child_(child), read_fd_(read_fd) {}
  void abandon();

  pid_t child_ = -1;
  int read_fd_ = -1;
};

}  // namespace stereomap::common
