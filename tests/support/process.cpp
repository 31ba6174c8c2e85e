#include "tests/support/process.hpp"

#include <filesystem>
#include <fstream>

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <signal.h>
#include <spawn.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <stdexcept>
#include <thread>

extern char** environ;

namespace stereomap::testing {

namespace fs = std::filesystem;

ChildProcess::ChildProcess(std::vector<std::string> argv, const std::string& log_path) {
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, STDOUT_FILENO, log_path.c_str(),
                                   O_WRONLY | O_CREAT | O_APPEND, 0644);
  posix_spawn_file_actions_adddup2(&actions, STDOUT_FILENO, STDERR_FILENO);
  // The child must not inherit a blocked SIGTERM/SIGINT from a test that blocked them.
  posix_spawnattr_t attributes;
  posix_spawnattr_init(&attributes);
  sigset_t empty;
  sigemptyset(&empty);
  posix_spawnattr_setsigmask(&attributes, &empty);
  posix_spawnattr_setflags(&attributes, POSIX_SPAWN_SETSIGMASK);
  std::vector<char*> args;
  for (auto& arg : argv) args.push_back(arg.data());
  args.push_back(nullptr);
  const int rc = posix_spawn(&pid_, args[0], &actions, &attributes, args.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  posix_spawnattr_destroy(&attributes);
  if (rc != 0) throw std::runtime_error("cannot start " + argv[0] + ": " + std::strerror(rc));
}

ChildProcess::~ChildProcess() {
  if (running()) stop(std::chrono::seconds(5));
}

bool ChildProcess::running() { return !waitExit(std::chrono::milliseconds(0)).has_value(); }

std::optional<int> ChildProcess::waitExit(std::chrono::milliseconds timeout) {
  if (status_) return status_;
  const auto deadline = std::chrono::steady_clock::now() + scaledTimeout(timeout);
  for (;;) {
    int status = 0;
    const pid_t done = waitpid(pid_, &status, WNOHANG);
    if (done == pid_) {
      status_ = WIFEXITED(status) ? WEXITSTATUS(status) : -WTERMSIG(status);
      return status_;
    }
    if (std::chrono::steady_clock::now() >= deadline) return std::nullopt;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));  // waitpid has no timeout
  }
}

int ChildProcess::stop(std::chrono::milliseconds grace) {
  if (!running()) return *status_;
  ::kill(pid_, SIGTERM);
  if (auto code = waitExit(grace)) return *code;
  kill9();
  return *status_;
}

void ChildProcess::kill9() {
  if (!running()) return;
  ::kill(pid_, SIGKILL);
  waitExit(std::chrono::seconds(10));
}

HttpReply httpGet(int port, const std::string& path) { return httpRequest(port, "GET", path); }

namespace {

// A TCP connection to 127.0.0.1:port with a 60 s receive timeout (session management replays
// journals: allow for it); -1 when it cannot be made.
int connectLoopback(int port) {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  if (fd < 0) return -1;
  timeval timeout{60, 0};
  setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &timeout, sizeof(timeout));
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(static_cast<uint16_t>(port));
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (::connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)) != 0) {
    ::close(fd);
    return -1;
  }
  return fd;
}

}  // namespace

HttpReply httpRequest(int port, const std::string& method, const std::string& path,
                      const std::string& body, const std::string& headers) {
  HttpReply reply;
  const int fd = connectLoopback(port);
  if (fd < 0) return reply;
  const std::string request =
      method + " " + path + " HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n" + headers +
      "Content-Type: application/json\r\nContent-Length: " + std::to_string(body.size()) +
      "\r\n\r\n" + body;
  if (::send(fd, request.data(), request.size(), 0) != static_cast<ssize_t>(request.size())) {
    ::close(fd);
    return reply;
  }
  std::string response;
  char buffer[65536];
  for (ssize_t n; (n = ::recv(fd, buffer, sizeof(buffer), 0)) > 0;) response.append(buffer, n);
  ::close(fd);
  const size_t header_end = response.find("\r\n\r\n");
  // HTTP/1.0 too (Patroni's REST API, Python's BaseHTTPServer).
  if ((response.rfind("HTTP/1.1 ", 0) != 0 && response.rfind("HTTP/1.0 ", 0) != 0) ||
      header_end == std::string::npos) {
    return reply;
  }
  reply.status = std::atoi(response.c_str() + 9);
  reply.headers = response.substr(0, header_end + 2);
  reply.body = response.substr(header_end + 4);
  return reply;
}

HttpConnection::~HttpConnection() {
  if (fd_ >= 0) ::close(fd_);
}

bool HttpConnection::connect() {
  if (fd_ >= 0) ::close(fd_);
  pending_.clear();
  fd_ = connectLoopback(port_);
  return fd_ >= 0;
}

HttpReply HttpConnection::get(const std::string& path) {
  const std::string request = "GET " + path + " HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n";
  for (int attempt = 0; attempt < 2; ++attempt) {
    if (fd_ < 0 && !connect()) return {};
    if (::send(fd_, request.data(), request.size(), MSG_NOSIGNAL) !=
        static_cast<ssize_t>(request.size())) {
      ::close(fd_);
      fd_ = -1;
      continue;
    }
    char buffer[65536];
    size_t header_end = std::string::npos;
    while ((header_end = pending_.find("\r\n\r\n")) == std::string::npos) {
      const ssize_t n = ::recv(fd_, buffer, sizeof(buffer), 0);
      if (n <= 0) break;
      pending_.append(buffer, static_cast<size_t>(n));
    }
    if (header_end == std::string::npos) {  // closed by the server: once more, anew
      ::close(fd_);
      fd_ = -1;
      continue;
    }
    HttpReply reply;
    reply.status = pending_.rfind("HTTP/1.1 ", 0) == 0 ? std::atoi(pending_.c_str() + 9) : 0;
    reply.headers = pending_.substr(0, header_end + 2);
    const size_t length = static_cast<size_t>(std::atoll(reply.header("Content-Length").c_str()));
    pending_.erase(0, header_end + 4);
    while (pending_.size() < length) {
      const ssize_t n = ::recv(fd_, buffer, sizeof(buffer), 0);
      if (n <= 0) break;
      pending_.append(buffer, static_cast<size_t>(n));
    }
    reply.body = pending_.substr(0, length);
    pending_.erase(0, std::min(length, pending_.size()));
    if (reply.header("Connection") == "close") {
      ::close(fd_);
      fd_ = -1;
    }
    return reply;
  }
  return {};
}

std::string HttpReply::header(const std::string& name) const {
  auto lower = [](std::string text) {
    for (auto& c : text) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
    return text;
  };
  const std::string wanted = lower(name) + ":";
  for (size_t at = 0; at < headers.size();) {
    const size_t end = headers.find("\r\n", at);
    const std::string line = headers.substr(at, end - at);
    if (lower(line.substr(0, wanted.size())) == wanted) {
      const size_t value = line.find_first_not_of(' ', wanted.size());
      return value == std::string::npos ? "" : line.substr(value);
    }
    if (end == std::string::npos) break;
    at = end + 2;
  }
  return "";
}

ToolRun runTool(const std::vector<std::string>& argv, std::chrono::milliseconds timeout) {
  const std::string dir = makeTempDir("stereomap-tool");
  const std::string log = dir + "/output.log";
  ToolRun run;
  {
    ChildProcess child(argv, log);
    run.exit_code = child.waitExit(timeout).value_or(-1);
  }
  std::ifstream in(log);
  run.output.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  std::error_code ec;
  std::filesystem::remove_all(dir, ec);
  return run;
}

bool waitUntil(std::chrono::milliseconds timeout, const std::function<bool()>& done,
               std::chrono::milliseconds step) {
  const auto deadline = std::chrono::steady_clock::now() + scaledTimeout(timeout);
  while (!done()) {
    if (std::chrono::steady_clock::now() >= deadline) return false;
    std::this_thread::sleep_for(step);  // polling a remote process: nothing to wait on
  }
  return true;
}

std::chrono::milliseconds scaledTimeout(std::chrono::milliseconds timeout) {
  static const int scale = [] {
    const char* text = std::getenv("STEREOMAP_TEST_TIME_SCALE");
    if (text == nullptr || *text == '\0') return 1;
    char* end = nullptr;
    const long value = std::strtol(text, &end, 10);
    if (*end != '\0' || value < 1 || value > 100)
      throw std::invalid_argument(std::string("STEREOMAP_TEST_TIME_SCALE must be a whole number "
                                              "from 1 to 100, not '") +
                                  text + "'");
    return static_cast<int>(value);
  }();
  return timeout * scale;
}

std::string makeTempDir(const std::string& prefix) {
  const char* tmp = std::getenv("TMPDIR");
  std::string pattern = std::string(tmp ? tmp : "/tmp") + "/" + prefix + "-XXXXXX";
  if (mkdtemp(pattern.data()) == nullptr) throw std::runtime_error("mkdtemp failed");
  return pattern;
}

// The processes whose parent is `parent` (from /proc/PID/stat: "pid (comm) state ppid ...").
std::vector<pid_t> childrenOf(pid_t parent) {
  std::vector<pid_t> children;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator("/proc", ec)) {
    const std::string name = entry.path().filename().string();
    if (name.find_first_not_of("0123456789") != std::string::npos) continue;
    std::ifstream in(entry.path() / "stat");
    std::string stat((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    const auto close = stat.rfind(')');
    if (close == std::string::npos) continue;
    char state = 0;
    long ppid = 0;
    if (std::sscanf(stat.c_str() + close + 1, " %c %ld", &state, &ppid) == 2 && ppid == parent) {
      children.push_back(static_cast<pid_t>(std::stol(name)));
    }
  }
  return children;
}

// True once `pid` is gone or a zombie: its sockets are closed either way.
bool isDead(pid_t pid) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/stat");
  std::string stat((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const auto close = stat.rfind(')');
  return close == std::string::npos || stat.compare(close + 1, 3, " Z ") == 0;
}

void killWithChildren(pid_t parent) {
  const std::vector<pid_t> children = childrenOf(parent);
  ::kill(parent, SIGKILL);
  for (pid_t child : children) ::kill(child, SIGKILL);
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  for (pid_t pid : children) {
    while (!isDead(pid) && std::chrono::steady_clock::now() < deadline) {
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
  }
  while (!isDead(parent) && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
}

void signalWithChildren(pid_t parent, int signal) {
  // Stopping: the parent first, so that it starts no new child meanwhile; continuing: last.
  if (signal == SIGSTOP) ::kill(parent, signal);
  for (pid_t child : childrenOf(parent)) ::kill(child, signal);
  if (signal != SIGSTOP) ::kill(parent, signal);
}

std::string replaced(std::string text, const std::string& from, const std::string& to) {
  for (size_t at = text.find(from); at != std::string::npos; at = text.find(from, at + to.size())) {
    text.replace(at, from.size(), to);
  }
  return text;
}

}  // namespace stereomap::testing
