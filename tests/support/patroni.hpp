// The cluster's database failing over for tests and benchmarks: a PostgreSQL primary with
// synchronous standbys, each under Patroni (config/patroni/stereomap-patroni.yml.in), and one
// etcd (its v2 API) holding the leader key; all throwaway, on loopback, as an unprivileged
// user. Servers reach it with one multi-host URL (target_session_attrs=read-write): libpq finds
// the primary, wherever Patroni has put it.
//
//   auto db = TestPatroni::start(3, &why);  // nullptr + why when Patroni or etcd is absent
//   db->crash();                            // the primary's PostgreSQL killed: a standby takes
//   db->restart(&why);                      // over; back to three nodes streaming
#pragma once

#include <chrono>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "tests/support/postgres.hpp"
#include "tests/support/process.hpp"

namespace stereomap::testing {

class TestPatroni : public TestDatabase {
 public:
  // etcd and `nodes` PostgreSQL nodes (at least 2); returns once one is the primary and every
  // other streams from it, one of them synchronously.
  static std::unique_ptr<TestPatroni> start(int nodes, std::string* why);
  ~TestPatroni() override;  // every process stopped, the directory removed

  std::string url(const std::string& database = "postgres") const override;
  std::optional<std::string> sql(const std::string& statement,
                                 const std::string& database = "postgres") override;
  void crash() override;   // the primary's PostgreSQL (Patroni goes on and fails it over)
  void pause() override;   // the primary's PostgreSQL hangs
  void resume() override;  // the one paused
  // Waits until every node runs again, one the primary and the others streaming from it.
  bool restart(std::string* why = nullptr) override;

  // The node that is primary now (Patroni's REST API), nullopt when none is.
  std::optional<int> primary();
  int nodes() const { return static_cast<int>(nodes_.size()); }

 private:
  struct Node {
    std::string name, data;
    int pg_port = 0, rest_port = 0;
    std::unique_ptr<ChildProcess> patroni;
  };
  TestPatroni() = default;
  bool startNode(Node& node, std::string* why);
  // Every node's role and state as Patroni's REST API says (GET /cluster on any node).
  bool healthy();
  // The postmaster's pid of `node`'s PostgreSQL (its postmaster.pid), 0 when not running.
  pid_t postmasterOf(const Node& node) const;
  std::string dir_, bin_, password_, scope_;
  int etcd_port_ = 0, etcd_peer_port_ = 0;
  std::unique_ptr<ChildProcess> etcd_;
  std::vector<Node> nodes_;
  pid_t paused_ = 0;
};

}  // namespace stereomap::testing
