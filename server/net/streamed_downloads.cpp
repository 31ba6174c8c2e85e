#include "server/net/streamed_downloads.hpp"

#include <sys/socket.h>
#include <sys/time.h>
#include <unistd.h>

#include <cstdio>

#include "server/core/api.hpp"

namespace stereomap::net {

namespace {

// Every byte, or false (the peer is gone, or took nothing within the send timeout).
bool sendAll(int fd, std::string_view bytes) {
  while (!bytes.empty()) {
    const ssize_t sent = ::send(fd, bytes.data(), bytes.size(), MSG_NOSIGNAL);
    if (sent <= 0) return false;
    bytes.remove_prefix(static_cast<size_t>(sent));
  }
  return true;
}

const char* reason(int status) {
  switch (status) {
    case 404:
      return "Not Found";
    case 409:
      return "Conflict";
    case 501:
      return "Not Implemented";
    case 503:
      return "Service Unavailable";
    default:
      return "Internal Server Error";
  }
}

int statusOf(common::ErrorCode code) {
  switch (code) {
    case common::ErrorCode::kNotFound:
      return 404;
    case common::ErrorCode::kConflict:
      return 409;
    case common::ErrorCode::kUnavailable:
      return 503;
    default:
      return 500;
  }
}

// One download: the header, the body in chunks of kChunkBytes, the last chunk.
void serve(int fd, const std::string& content_type, const std::string& filename,
           const StreamedBody& body) {
  const timeval timeout{static_cast<time_t>(StreamedDownloads::kStalledAfter.count()), 0};
  ::setsockopt(fd, SOL_SOCKET, SO_SNDTIMEO, &timeout, sizeof timeout);
  bool started = false, gone = false;
  std::string pending;
  auto flush = [&] {
    if (pending.empty() || gone) return;
    char size[24];
    std::snprintf(size, sizeof size, "%zx\r\n", pending.size());
    gone = !sendAll(fd, size) || !sendAll(fd, pending) || !sendAll(fd, "\r\n");
    pending.clear();
  };
  auto sink = [&](std::string_view bytes) {
    if (gone) return false;
    if (!started) {
      started = true;
      const std::string header =
          "HTTP/1.1 200 OK\r\nServer: stereomap\r\nContent-Type: " + content_type +
          "\r\nContent-Disposition: attachment; filename=\"" + filename +
          "\"\r\nCache-Control: no-store\r\nTransfer-Encoding: chunked\r\nConnection: "
          "close\r\n\r\n";
      gone = !sendAll(fd, header);
    }
    pending.append(bytes);
    if (pending.size() >= StreamedDownloads::kChunkBytes) flush();
    return !gone;
  };
  const common::Status status = body(sink);
  if (status) {
    if (!started) sink({});
    flush();
    if (!gone) sendAll(fd, "0\r\n\r\n");
  } else if (!started) {
    sendAll(fd, errorAnswer(statusOf(status.error().code), status.error().message));
  }  // else: cut short, so the client never takes half a file for a whole one
}

}  // namespace

std::string errorAnswer(int status, const std::string& message) {
  const std::string body = core::errorBody(message);
  return "HTTP/1.1 " + std::to_string(status) + " " + reason(status) +
         "\r\nServer: stereomap\r\nContent-Type: application/json\r\nContent-Length: " +
         std::to_string(body.size()) + "\r\nConnection: close\r\n\r\n" + body;
}

void refuseDownload(int fd, int status, const std::string& message) {
  const timeval timeout{5, 0};  // a few hundred bytes: the socket's buffer takes them at once
  ::setsockopt(fd, SOL_SOCKET, SO_SNDTIMEO, &timeout, sizeof timeout);
  sendAll(fd, errorAnswer(status, message));
  ::shutdown(fd, SHUT_RDWR);
  ::close(fd);
}

bool StreamedDownloads::start(int fd, std::string content_type, std::string filename,
                              StreamedBody body) {
  std::lock_guard lock(mutex_);
  reap();
  if (stopped_ || running_.size() >= kMaxRunning) return false;
  auto* run = new Running{fd, {}};
  running_.push_back(run);
  run->thread = std::thread([this, run, content_type = std::move(content_type),
                             filename = std::move(filename), body = std::move(body)] {
    serve(run->fd, content_type, filename, body);
    // Closed under the lock: stop() never shuts down a descriptor already reused.
    std::lock_guard lock(mutex_);
    ::shutdown(run->fd, SHUT_RDWR);
    ::close(run->fd);
    run->done = true;
  });
  return true;
}

void StreamedDownloads::reap() {
  for (auto it = running_.begin(); it != running_.end();) {
    if ((*it)->done) {
      (*it)->thread.join();
      delete *it;
      it = running_.erase(it);
    } else {
      ++it;
    }
  }
}

void StreamedDownloads::stop() {
  std::vector<Running*> running;
  {
    std::lock_guard lock(mutex_);
    stopped_ = true;
    // A download blocked in send() returns at once; one still making its body stops at its
    // next write.
    for (Running* run : running_) {
      if (!run->done) ::shutdown(run->fd, SHUT_RDWR);
    }
    running.swap(running_);
  }
  for (Running* run : running) {
    run->thread.join();
    delete run;
  }
}

}  // namespace stereomap::net
