// Helpers for cross-process tests: a child process that is always cleaned up (SIGTERM, then
// SIGKILL), a plain HTTP GET against the server on loopback, and waiting with a deadline.
//
// Deadlines that bound waiting for work to finish (waitExit, waitUntil, runTool, a server's
// start) are stretched by STEREOMAP_TEST_TIME_SCALE (a whole number 1-100, default 1):
// scripts/sanitize sets it, as an instrumented vehicle runs 10-20 times slower. A test that
// measures against a time budget must not rely on these for its measurement.
#pragma once

#include <chrono>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include <sys/types.h>

namespace stereomap::testing {

class ChildProcess {
 public:
  // Starts `argv[0]` with the arguments; stdout and stderr go to `log_path` (appended).
  ChildProcess(std::vector<std::string> argv, const std::string& log_path);
  ~ChildProcess();  // stops the process if it still runs
  ChildProcess(const ChildProcess&) = delete;
  ChildProcess& operator=(const ChildProcess&) = delete;

  bool running();
  // Waits for exit up to `timeout`; the exit code, or nullopt if it is still running.
  std::optional<int> waitExit(std::chrono::milliseconds timeout);
  // SIGTERM, wait up to `grace`, then SIGKILL. Returns the exit code (or -signal).
  int stop(std::chrono::milliseconds grace = std::chrono::seconds(10));
  void kill9();
  pid_t pid() const { return pid_; }

 private:
  pid_t pid_ = -1;
  std::optional<int> status_;
};

// Runs a command to completion (killed after `timeout`): its exit code (-1 when it had to be
// killed) and its stdout + stderr.
struct ToolRun {
  int exit_code = -1;
  std::string output;
};
ToolRun runTool(const std::vector<std::string>& argv,
                std::chrono::milliseconds timeout = std::chrono::seconds(120));

struct HttpReply {
  int status = 0;  // 0: no answer
  std::string body;
  std::string headers;  // the response's header lines, as received
  // A header's value ("" when absent); `name` is matched without regard to case.
  std::string header(const std::string& name) const;
};

// GET (or `method`, with a JSON body) http://127.0.0.1:port/path with a 60 s timeout;
// status 0 when nothing answered. `path` is sent exactly as given (no normalisation);
// `headers` are extra "Name: value\r\n" lines.
HttpReply httpGet(int port, const std::string& path);
HttpReply httpRequest(int port, const std::string& method, const std::string& path,
                      const std::string& body = "", const std::string& headers = "");

// A keep-alive HTTP/1.1 connection to 127.0.0.1:port for many GETs in a row (load tests:
// no handshake per request). Answers must carry Content-Length; it connects again after a
// server closes the connection.
class HttpConnection {
 public:
  explicit HttpConnection(int port) : port_(port) {}
  ~HttpConnection();
  HttpConnection(const HttpConnection&) = delete;
  HttpConnection& operator=(const HttpConnection&) = delete;
  HttpReply get(const std::string& path);

 private:
  bool connect();
  int port_ = 0;
  int fd_ = -1;
  std::string pending_;  // bytes read past the previous answer
};

// Calls `done` until it returns true or `timeout` passes; true when it did.
bool waitUntil(std::chrono::milliseconds timeout, const std::function<bool()>& done,
               std::chrono::milliseconds step = std::chrono::milliseconds(200));

// `timeout` times STEREOMAP_TEST_TIME_SCALE; throws std::invalid_argument naming the variable
// when it is set to anything but a whole number from 1 to 100.
std::chrono::milliseconds scaledTimeout(std::chrono::milliseconds timeout);

// A fresh empty directory under $TMPDIR, removed by the caller.
std::string makeTempDir(const std::string& prefix);

// The processes whose parent is `parent` (from /proc).
std::vector<pid_t> childrenOf(pid_t parent);
// True once `pid` is gone or a zombie: its sockets are closed either way.
bool isDead(pid_t pid);
// `parent` and its children killed at once (SIGKILL), as in a crash of their machine; returns
// once they are dead (their sockets closed), or after 10 s.
void killWithChildren(pid_t parent);
// `signal` to `parent` and its children (SIGSTOP: a machine that hangs; SIGCONT: it resumes).
void signalWithChildren(pid_t parent, int signal);
// `text` with every `from` replaced by `to` (filling a configuration template).
std::string replaced(std::string text, const std::string& from, const std::string& to);

}  // namespace stereomap::testing
