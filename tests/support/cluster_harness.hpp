// A whole cluster on loopback for tests and the cluster's benchmarks: a throwaway database (one
// PostgreSQL, or a primary with synchronous standbys under Patroni), stereomap-server
// --cluster processes, nginx in front of them (config/nginx), sim vehicles; what the database
// says of owners, and a viewer's view through the proxy.
#pragma once

#include <chrono>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "tests/support/nginx.hpp"
#include "tests/support/patroni.hpp"
#include "tests/support/postgres.hpp"
#include "tests/support/server_fixture.hpp"

namespace stereomap::testing {

class ClusterHarness {
 public:
  // Starts the database (`patroni_nodes` > 0: that many nodes under Patroni; else one
  // PostgreSQL); nullptr with `why` when it cannot.
  static std::unique_ptr<ClusterHarness> start(std::string* why, int patroni_nodes = 0);
  ~ClusterHarness();  // vehicles, nginx, servers, then the database

  // A server with --server-id `id` on `domain`, with a lease of `lease_s` seconds, known here
  // as `name` (default: its id; another name for a second process under one id).
  ServerProcess& startServer(int domain, const std::string& id, double lease_s = 2,
                             const std::string& name = "",
                             const std::vector<std::string>& extra_args = {});
  ServerProcess& server(const std::string& id) { return *servers_.at(id); }
  // The server known as `name`, no longer the harness's (a process replaced by a new one under
  // its name, kept by the caller until it ends).
  std::unique_ptr<ServerProcess> takeServer(const std::string& name);
  std::map<std::string, std::unique_ptr<ServerProcess>>& servers() { return servers_; }
  // nginx in front of every server started so far.
  bool startNginx(std::string* why);
  TestNginx& nginx() { return *nginx_; }
  TestDatabase& db() { return *db_; }
  const std::string& dir() const { return dir_; }

  // Vehicle `i` flying session flight<i> as users fly it, `frames` frames at 10 Hz, with its
  // trajectory written out.
  void startVehicle(int domain, int i, int frames);
  std::string vehicleLog(int i) const;
  // The poses vehicle `i` sent (its --trajectory-out, TUM), written when it ends.
  std::string trajectoryOut(int i) const;
  // Vehicle `i`'s process (running, or ended).
  ChildProcess& vehicle(int i) { return *vehicles_.at(static_cast<size_t>(i)); }
  // Waits for every vehicle to end; false (with its log in `why`) when one failed.
  bool waitForVehicles(std::chrono::seconds timeout, std::string* why);

  // The live sessions' owners (session -> server id) as the database says.
  std::map<std::string, std::string> owners();
  // True once every session is owned by `server`.
  bool allOwnedBy(const std::string& server);
  // The output of one statement (psql, tuples only), "" when it fails.
  std::string query(const std::string& sql);

 private:
  ClusterHarness() = default;
  std::unique_ptr<TestDatabase> db_;
  std::string dir_;
  std::map<std::string, std::unique_ptr<ServerProcess>> servers_;
  std::unique_ptr<TestNginx> nginx_;
  std::vector<std::unique_ptr<ChildProcess>> vehicles_;
};

// A viewer connecting through the proxy as the web viewer does (/ws?session=ID, hello,
// subscribe, a view): true when a tile of `session` came within `timeout`.
bool viewerSeesTiles(int port, const std::string& session, std::chrono::milliseconds timeout);

}  // namespace stereomap::testing
