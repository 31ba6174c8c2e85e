#include "common/forked_write.hpp"

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <ostream>
#include <streambuf>
#include <utility>

#include "common/files.hpp"

namespace stereomap::common {

namespace {

// An unbuffered-by-libc stream buffer over a file descriptor (the child's pipe end).
class FdWriteBuffer : public std::streambuf {
 public:
  explicit FdWriteBuffer(int fd) : fd_(fd) { setp(buffer_, buffer_ + sizeof(buffer_)); }
  bool flushAll() { return sync() == 0; }

 protected:
  int_type overflow(int_type c) override {
    if (!drain()) return traits_type::eof();
    if (!traits_type::eq_int_type(c, traits_type::eof())) {
      *pptr() = traits_type::to_char_type(c);
      pbump(1);
    }
    return traits_type::not_eof(c);
  }
  int sync() override { return drain() ? 0 : -1; }

 private:
  bool drain() {
    for (const char* at = pbase(); at < pptr();) {
      const ssize_t n = ::write(fd_, at, static_cast<size_t>(pptr() - at));
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) return false;
      at += n;
    }
    setp(buffer_, buffer_ + sizeof(buffer_));
    return true;
  }
  int fd_;
  char buffer_[1 << 16];
};

[[noreturn]] void runChild(int write_fd, pid_t parent,
                           const std::function<bool(std::ostream&)>& write) {
  // Die with the parent; it may have died before the request took effect.
  ::prctl(PR_SET_PDEATHSIG, SIGKILL);
  if (::getppid() != parent) ::_exit(3);
  // Hold none of the parent's sockets, journals or listening ports.
  if (write_fd > 3) ::close_range(3, static_cast<unsigned>(write_fd) - 1, 0);
  ::close_range(static_cast<unsigned>(write_fd) + 1, ~0u, 0);
  FdWriteBuffer buffer(write_fd);
  std::ostream out(&buffer);
  const bool written = write(out) && out.good() && buffer.flushAll();
  ::_exit(written ? 0 : 1);
}

}  // namespace

Result<ForkedWrite> ForkedWrite::start(const std::function<bool(std::ostream&)>& write) {
  int fds[2];
  if (::pipe2(fds, O_CLOEXEC) != 0) {
    return makeError(ErrorCode::kUnavailable, "pipe: " + systemError(errno));
  }
  const pid_t parent = ::getpid();
  const pid_t child = ::fork();
  if (child < 0) {
    const int error = errno;
    ::close(fds[0]);
    ::close(fds[1]);
    return makeError(ErrorCode::kUnavailable, "fork: " + systemError(error));
  }
  if (child == 0) {
    ::close(fds[0]);
    runChild(fds[1], parent, write);
  }
  ::close(fds[1]);
  return ForkedWrite(child, fds[0]);
}

ForkedWrite::ForkedWrite(ForkedWrite&& other) noexcept
    : child_(std::exchange(other.child_, -1)), read_fd_(std::exchange(other.read_fd_, -1)) {}

ForkedWrite& ForkedWrite::operator=(ForkedWrite&& other) noexcept {
  if (this != &other) {
    abandon();
    child_ = std::exchange(other.child_, -1);
    read_fd_ = std::exchange(other.read_fd_, -1);
  }
  return *this;
}

ForkedWrite::~ForkedWrite() { abandon(); }

void ForkedWrite::abandon() {
  if (read_fd_ >= 0) ::close(read_fd_);
  read_fd_ = -1;
  if (child_ > 0) {
    ::kill(child_, SIGKILL);
    while (::waitpid(child_, nullptr, 0) < 0 && errno == EINTR) {
    }
  }
  child_ = -1;
}

Result<std::string> ForkedWrite::finish(std::optional<std::chrono::milliseconds> deadline) {
  if (child_ <= 0) return makeError(ErrorCode::kInvalidArgument, "nothing to collect");
  using Clock = std::chrono::steady_clock;
  const auto until = deadline ? Clock::now() + *deadline : Clock::time_point::max();
  std::string bytes;
  int read_error = 0;
  char chunk[1 << 16];
  for (;;) {
    if (deadline) {
      const auto left = std::chrono::ceil<std::chrono::milliseconds>(until - Clock::now()).count();
      pollfd readable{.fd = read_fd_, .events = POLLIN, .revents = 0};
      const int ready = left > 0 ? ::poll(&readable, 1, static_cast<int>(left)) : 0;
      if (ready < 0 && errno == EINTR) continue;
      if (ready < 0) {
        const int error = errno;
        abandon();  // a child that may never finish is not waited for
        return makeError(ErrorCode::kIo, "waiting for the forked child: " + systemError(error));
      }
      if (ready == 0) {
        abandon();  // kills and reaps the child
        return makeError(ErrorCode::kUnavailable, "the forked child did not finish within " +
                                                      std::to_string(deadline->count()) + " ms");
      }
    }
    const ssize_t n = ::read(read_fd_, chunk, sizeof(chunk));
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) read_error = errno;
    if (n <= 0) break;
    bytes.append(chunk, static_cast<size_t>(n));
  }
  ::close(read_fd_);
  read_fd_ = -1;
  int status = 0;
  pid_t reaped;
  while ((reaped = ::waitpid(child_, &status, 0)) < 0 && errno == EINTR) {
  }
  child_ = -1;
  if (read_error != 0) {
    return makeError(ErrorCode::kIo, "reading the forked writer: " + systemError(read_error));
  }
  if (reaped < 0 || !WIFEXITED(status) || WEXITSTATUS(status) != 0) {
    return makeError(
        ErrorCode::kIo,
        WIFSIGNALED(status)
            ? "the forked writer was killed by signal " + std::to_string(WTERMSIG(status))
            : "the forked writer failed (exit " +
                  std::to_string(WIFEXITED(status) ? WEXITSTATUS(status) : -1) + ")");
  }
  return bytes;
}

}  // namespace stereomap::common
