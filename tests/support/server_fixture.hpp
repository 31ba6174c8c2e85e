// A stereomap-server process for cross-process tests: started on a free port and its own
// DDS domain, with a temporary store, and stopped (and checked) at the end.
//
// ctest runs tests side by side, so every test that talks DDS has a domain of its own: 61-62
// proto, 71/93 map accuracy, 72/84/88 bad input, 73 browser, 74/85 crash recovery, 75 session
// admin, 76/79 security, 77/78/80 durability, 83 tiles over HTTP, 86 test-docker, 87/89 pose
// graph end to end, 90/92 landing end to end, 94/95 shaped link, 96 the soak run (tests/soak),
// 98-102 outages, 103-108 the cluster (tests, benchmark), 109 test-docker's cluster, 110
// the fleet benchmark's recordings (stereomap-bench-scale), 111 the MCAP export read by
// Foxglove's readers (tests/interop), 112 its benchmark (stereomap-bench-interop), 113-114
// Foxglove live (tests/interop), 122-129 DDS Security (tests/dds_security_test.cpp), 130 roles
// (tests/security_test.cpp), 131 nginx and tokens (tests/cluster_e2e_test.cpp), 132-133 TLS
// (tests/interop/tls_clients.mjs), 134 aligning sessions (tests/align_e2e_test.cpp), 135 frame
// acknowledgements (onboard/pipeline/pipeline_test.cpp), 136 a live join
// (tests/align_e2e_test.cpp), 137 its benchmark (stereomap-bench-align), 138 sites
// (tests/align_e2e_test.cpp). A new test takes a free
// one and adds it here.
#pragma once

#include <chrono>
#include <cstdlib>
#include <memory>
#include <string>
#include <vector>

#include "tests/support/process.hpp"

namespace stereomap::testing {

class ServerProcess {
 public:
  // Starts the server and waits until it answers /healthz (200, or any answer when
  // `require_healthy` is false: a degraded store); throws with the log on failure.
  // With `store` given the server uses (and the fixture keeps) that directory; otherwise a
  // temporary one, removed at the end. `start_within`: how long recovery may take.
  ServerProcess(int domain, const std::vector<std::string>& extra_args = {},
                const std::string& store = "", bool require_healthy = true,
                std::chrono::seconds start_within = std::chrono::seconds(20));
  ~ServerProcess();
  int port() const { return port_; }
  const std::string& store() const { return store_; }
  const std::string& logPath() const { return log_; }
  std::string log() const;
  HttpReply get(const std::string& path) const { return httpGet(port_, path); }
  HttpReply request(const std::string& method, const std::string& path,
                    const std::string& body = "", const std::string& headers = "") const {
    return httpRequest(port_, method, path, body, headers);
  }
  ChildProcess& process() { return *process_; }

 private:
  std::string store_;
  bool owns_store_ = true;
  std::string log_;
  int port_ = 0;
  std::unique_ptr<ChildProcess> process_;
};

// The value of one series in Prometheus text (`name{labels}`, or `name` alone), 0 when
// absent. Matched at a line's start: a family's "# HELP name ..." line is not its value.
inline double seriesValue(const std::string& metrics, const std::string& series) {
  for (size_t at = metrics.find(series + " "); at != std::string::npos;
       at = metrics.find(series + " ", at + 1)) {
    if (at == 0 || metrics[at - 1] == '\n') {
      return std::atof(metrics.c_str() + at + series.size() + 1);
    }
  }
  return 0.0;
}

// The onboard binary's argv for a sim flight on `domain`.
std::vector<std::string> onboardArgs(int domain, const std::string& session, int frames,
                                     const std::vector<std::string>& extra = {});

}  // namespace stereomap::testing
