// nginx in front of a cluster for tests and benchmarks: config/nginx/stereomap-cluster.conf.in
// filled in (a fresh prefix folder, 127.0.0.1 and a free port, the servers given), run in the
// foreground as an unprivileged user when the test runs as root. Stopped with the object.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "tests/support/process.hpp"

namespace stereomap::testing {

class TestNginx {
 public:
  // `upstreams`: "127.0.0.1:PORT" of each server. nullopt with `why` when nginx is absent or
  // does not start (its error log is named).
  static std::unique_ptr<TestNginx> start(const std::vector<std::string>& upstreams,
                                          std::string* why);
  ~TestNginx();
  TestNginx(const TestNginx&) = delete;
  TestNginx& operator=(const TestNginx&) = delete;

  int port() const { return port_; }
  const std::string& prefix() const { return prefix_; }
  // The access log's lines (status, cache status, time, request, upstream).
  std::string accessLog() const;
  // Killed (with its workers) and started again on the same port and cache.
  bool restart(std::string* why = nullptr);

 private:
  TestNginx() = default;
  bool launch(std::string* why);
  std::vector<std::string> argv_;
  std::string prefix_;
  int port_ = 0;
  std::unique_ptr<ChildProcess> process_;
};

}  // namespace stereomap::testing
