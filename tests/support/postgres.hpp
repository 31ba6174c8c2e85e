// A throwaway PostgreSQL 15 for tests and benchmarks of the cluster: initdb into a fresh
// temporary directory, password authentication (scram-sha-256), listening on 127.0.0.1 at a
// free port, WAL flushed on commit as in production. PostgreSQL refuses to run as root, so a
// test running as root runs it as `nobody`. Stopped and removed with the object.
//
//   auto db = TestPostgres::start();       // nullopt + why when PostgreSQL is not installed
//   std::string url = db->url();           //
//   postgresql://stereomap:PASSWORD@127.0.0.1:PORT/postgres db->crash(); db->restart(); // the
//   database failing under a running cluster
#pragma once

#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "tests/support/process.hpp"

namespace stereomap::testing {

// The cluster's database as tests and benchmarks drive it: one PostgreSQL (TestPostgres), or a
// primary with synchronous standbys under Patroni (TestPatroni, patroni.hpp). Its faults are
// real processes killed, paused and started again.
class TestDatabase {
 public:
  virtual ~TestDatabase() = default;
  // libpq URL of database `database` (created by createDatabase, or "postgres"); under
  // Patroni every node, with target_session_attrs=read-write (libpq finds the primary).
  virtual std::string url(const std::string& database = "postgres") const = 0;
  // Runs one SQL statement with psql on the primary; its output (tuples only, unaligned),
  // nullopt on error.
  virtual std::optional<std::string> sql(const std::string& statement,
                                         const std::string& database = "postgres") = 0;
  // The primary's PostgreSQL killed: the postmaster and every backend at once, as in a crash
  // of its machine; returns once their sockets are closed.
  virtual void crash() = 0;
  // Every process of the primary's PostgreSQL stopped (SIGSTOP), as a machine that hangs:
  // connections stay open and new ones are accepted by the kernel, but nothing answers;
  // resume() continues them.
  virtual void pause() = 0;
  virtual void resume() = 0;
  // Whole again after crash(): PostgreSQL started again on the same directory and port, or,
  // under Patroni, every node back and streaming. False (with `why`) when it does not come up.
  virtual bool restart(std::string* why = nullptr) = 0;
  // Creates an empty database; false with the output in `why`.
  bool createDatabase(const std::string& name, std::string* why = nullptr);
};

class TestPostgres : public TestDatabase {
 public:
  // Initialises and starts one; nullopt with `why` set when PostgreSQL's binaries are absent
  // or it does not start (its log is named).
  static std::unique_ptr<TestPostgres> start(std::string* why);
  ~TestPostgres();
  TestPostgres(const TestPostgres&) = delete;
  TestPostgres& operator=(const TestPostgres&) = delete;

  std::string url(const std::string& database = "postgres") const override;
  // The same with a wrong password, for tests of refused credentials.
  std::string urlWithPassword(const std::string& password,
                              const std::string& database = "postgres") const;
  int port() const { return port_; }
  const std::string& dir() const { return dir_; }
  std::optional<std::string> sql(const std::string& statement,
                                 const std::string& database = "postgres") override;

  bool running();
  void stop();  // a clean shutdown (fast mode)
  // The postmaster killed; its backends notice at their next wait and exit, finishing the
  // statement under way (its client gets the answer).
  void kill9();
  // A connection is certainly lost, and a statement under way may have committed without its
  // client hearing so.
  void crash() override;
  void pause() override;
  void resume() override;
  bool restart(std::string* why = nullptr) override;

 private:
  TestPostgres() = default;
  bool launch(std::string* why);
  std::string bin_, dir_, password_;
  int port_ = 0;
  std::unique_ptr<ChildProcess> postmaster_;
};

// A TCP port on 127.0.0.1 that nothing listens on now.
int unusedPort();

// What TestPostgres and TestPatroni share: the newest PostgreSQL's binaries (Debian:
// /usr/lib/postgresql/<version>/bin; "" when absent), a password, the end of a log, and argv
// run as the user `nobody` when the test runs as root (PostgreSQL refuses to run as root).
std::string postgresBinDir();
std::string randomPassword();
std::string logTail(const std::string& path);
std::vector<std::string> asUnprivileged(std::vector<std::string> argv);
// One SQL statement run by psql (from `bin`) on `url`: its output (tuples only, unaligned),
// nullopt on error.
std::optional<std::string> runPsql(const std::string& bin, const std::string& url,
                                   const std::string& statement);
// Makes `dir` the unprivileged user's when the test runs as root; false when it cannot.
bool handToUnprivileged(const std::string& dir);

}  // namespace stereomap::testing
