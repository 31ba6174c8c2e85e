// A deployment secured by stereomap-certs, and what the security tests and
// stereomap-bench-security do with it (issue 55): vehicles flown with or without an identity,
// the attacker's probe (stereomap-dds-probe), the sessions a server took.
#pragma once

#include <string>
#include <vector>

#include "tests/support/server_fixture.hpp"

namespace stereomap::testing {

// A deployment in a new temporary folder: server s1, the vehicles named, and two more, "old"
// (its certificate expired in 2020) and "lost" (revoked: the CRL in s1's folder names it).
struct Deployment {
  std::string dir;
  std::string log;  // what stereomap-certs said
  bool ok = false;
  std::string server() const { return dir + "/servers/s1"; }
  std::string vehicle(const std::string& id) const { return dir + "/vehicles/" + id; }
};
Deployment makeDeployment(const std::vector<std::string>& vehicles);

// stereomap-dds-probe's output (its one line last) for `args` on `domain`, as `identity` (a
// participant folder) or with none.
std::string probe(const std::vector<std::string>& args, int domain,
                  const std::string& identity = "");

struct Flight {
  int exit_code = -1;
  std::string log;
};
// A sim vehicle `vehicle` flying `frames` frames into `session`, as `identity` or with none.
Flight fly(int domain, const std::string& session, const std::string& vehicle,
           const std::string& identity, int frames = 20,
           const std::vector<std::string>& extra = {});

// "N still unacknowledged" from a vehicle's summary, -1 when absent.
int unacknowledged(const std::string& log);

// The ids of the sessions `server` lists.
std::vector<std::string> sessionIds(const ServerProcess& server);

}  // namespace stereomap::testing
