// Downloads written as they are made (a session's MCAP export: minutes of journal, hundreds of
// MB), each on a thread of its own that owns the connection: HTTP/1.1 chunked transfer, so
// neither the file nor its length is ever held; the network thread and the other clients never
// wait for it. At most kMaxRunning at once (a further request is answered 503 at once). A client
// that takes nothing for kStalledAfter is dropped (the socket's send timeout), and stop() ends
// every download under way (their sockets are shut down, their threads joined).
#pragma once

#include <chrono>
#include <functional>
#include <mutex>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include "common/result.hpp"

namespace stereomap::net {

// Writes the download through `sink` (false: the client is gone; stop writing). An error
// before the first byte becomes the answer's status (kNotFound 404, kConflict 409,
// kUnavailable 503, else 500); after it, the connection is cut short (the client sees an
// unfinished transfer, never a complete-looking file).
using StreamedBody =
    std::function<common::Status(const std::function<bool(std::string_view)>& sink)>;

class StreamedDownloads {
 public:
  static constexpr size_t kMaxRunning = 2;
  static constexpr std::chrono::seconds kStalledAfter{30};
  static constexpr size_t kChunkBytes = 256u << 10;

  StreamedDownloads() = default;
  ~StreamedDownloads() { stop(); }
  StreamedDownloads(const StreamedDownloads&) = delete;
  StreamedDownloads& operator=(const StreamedDownloads&) = delete;

  // Takes the connected socket `fd` (closed at the end, whatever happens) and answers on it:
  // 200 with `content_type` and the download name `filename`, then the body. False (the fd
  // untouched) when kMaxRunning are under way or after stop().
  bool start(int fd, std::string content_type, std::string filename, StreamedBody body);
  void stop();  // idempotent

 private:
  struct Running {
    int fd;
    std::thread thread;
    bool done = false;
  };
  void reap();  // joins finished threads, under mutex_

  std::mutex mutex_;
  std::vector<Running*> running_;
  bool stopped_ = false;
};

// The whole answer for an error before the body (status line, JSON body, Connection: close).
std::string errorAnswer(int status, const std::string& message);
// Answers `fd` with that error and closes it (a download that cannot start).
void refuseDownload(int fd, int status, const std::string& message);

}  // namespace stereomap::net
