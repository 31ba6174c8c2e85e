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

#include "tests/support/process.hpp"

namespace stereomap::testing {

class TestPostgres {
 public:
  // Initialises and starts one; nullopt with `why` set when PostgreSQL's binaries are absent
  // or it does not start (its log is named).
  static std::unique_ptr<TestPostgres> start(std::string* why);
  ~TestPostgres();
  TestPostgres(const TestPostgres&) = delete;
  TestPostgres& operator=(const TestPostgres&) = delete;

  // libpq URL of database `database` (created by createDatabase, or "postgres").
  std::string url(const std::string& database = "postgres") const;
  // The same with a wrong password, for tests of refused credentials.
  std::string urlWithPassword(const std::string& password,
                              const std::string& database = "postgres") const;
  int port() const { return port_; }
  const std::string& dir() const { return dir_; }
  // Creates an empty database (psql); false with the output in `why`.
  bool createDatabase(const std::string& name, std::string* why = nullptr);
  // Runs one SQL statement with psql; its output (tuples only, unaligned), nullopt on error.
  std::optional<std::string> sql(const std::string& statement,
                                 const std::string& database = "postgres");

  bool running();
  void stop();  // a clean shutdown (fast mode)
  // The postmaster killed; its backends notice at their next wait and exit, finishing the
  // statement under way (its client gets the answer).
  void kill9();
  // The postmaster and every backend killed at once, as in a crash of the database's machine,
  // and returns once their sockets are closed: a connection is certainly lost, and a statement
  // under way may have committed without its client hearing so.
  void crash();
  // Every process of the database stopped (SIGSTOP), as a machine that hangs: connections stay
  // open and new ones are accepted by the kernel, but nothing answers; resume() continues them.
  void pause();
  void resume();
  // Starts it again on the same directory and port; false when it does not come up.
  bool restart(std::string* why = nullptr);

 private:
  TestPostgres() = default;
  bool launch(std::string* why);
  std::vector<std::string> asDatabaseUser(std::vector<std::string> argv) const;
  std::string bin_, dir_, password_;
  int port_ = 0;
  bool drop_root_ = false;
  std::unique_ptr<ChildProcess> postmaster_;
};

// A TCP port on 127.0.0.1 that nothing listens on now.
int unusedPort();

}  // namespace stereomap::testing
