// A PostgreSQL connection through libpq. Every statement takes its values as parameters,
// never pasted into the SQL text, so no id or payload from outside can change what a
// statement does. Results come back as text (bytea unescaped by bytes()).
//
// Every call has a deadline of the client's own (PgOptions): a database that hangs without
// closing its connections (a paused machine, a network that drops packets) answers nothing,
// and neither TCP nor the server's statement_timeout would end the wait. A statement past its
// deadline is abandoned: the connection is closed, and its backend is terminated (and waited
// for) before the next statement on a new connection, so that nothing it had under way can
// commit after the caller was told it failed.
//
//   auto db = PgConnection::connect("postgresql://sm@127.0.0.1:5432/stereomap");
//   auto rows = db->exec("SELECT epoch FROM sm_sessions WHERE id = $1", {session});
//   int64_t epoch = rows->integer(0, 0);
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "common/result.hpp"

struct pg_conn;
struct pg_result;

namespace stereomap::cluster {

// A statement's parameter: text, binary bytes (for bytea), or SQL NULL.
struct PgParam {
  PgParam(std::string text) : value(std::move(text)) {}        // NOLINT: implicit by design
  PgParam(const char* text) : value(text) {}                   // NOLINT
  PgParam(int64_t number) : value(std::to_string(number)) {}   // NOLINT
  PgParam(uint64_t number) : value(std::to_string(number)) {}  // NOLINT
  PgParam(int number) : value(std::to_string(number)) {}       // NOLINT
  PgParam(double number);                                      // NOLINT: exact (hex float)
  static PgParam bytes(std::string_view data);
  static PgParam null();
  std::optional<std::string> value;
  bool binary = false;
};

// What a statement returned (moved, never copied).
class PgResult {
 public:
  explicit PgResult(pg_result* result);
  ~PgResult();
  PgResult(PgResult&& other) noexcept;
  PgResult& operator=(PgResult&& other) noexcept;
  PgResult(const PgResult&) = delete;
  PgResult& operator=(const PgResult&) = delete;

  int rows() const;
  int columns() const;
  bool isNull(int row, int column) const;
  std::string text(int row, int column) const;
  int64_t integer(int row, int column) const;  // 0 for NULL
  double real(int row, int column) const;
  std::string bytes(int row, int column) const;  // a bytea column's bytes
  // Rows a statement changed (INSERT, UPDATE, DELETE).
  uint64_t affected() const;

 private:
  friend class PgConnection;
  pg_result* raw() const { return result_; }
  pg_result* result_ = nullptr;
};

// The SQLSTATE the database's fencing trigger raises when a write carries a stale epoch.
inline constexpr const char* kFencedState = "SMF01";
// The SQLSTATE of a unique violation: in the journal, another writer's row at that number.
inline constexpr const char* kUniqueViolationState = "23505";

struct PgOptions {
  // Connecting, authentication included (libpq counts whole seconds, at least 2).
  std::chrono::milliseconds connect_timeout{5000};
  // The longest any one exec() waits for its answer; also the server's statement_timeout
  // (plus a margin), so that the database gives up on it too.
  std::chrono::milliseconds deadline{10000};
  // The server's lock_timeout: a statement waiting on a lock held by a paused client gives up.
  std::chrono::milliseconds lock_timeout{2000};
};

class PgConnection {
 public:
  // Connects (a libpq URL or key=value string); the error says whether the server could not
  // be reached or refused the credentials, with libpq's words.
  static common::Result<std::unique_ptr<PgConnection>> connect(const std::string& url,
                                                               const PgOptions& options = {});
  ~PgConnection();
  PgConnection(const PgConnection&) = delete;
  PgConnection& operator=(const PgConnection&) = delete;

  // Runs one statement within options().deadline (or `deadline` when given). Errors:
  // kConflict for a fenced write (kFencedState) or a unique violation, kUnavailable when the
  // connection is lost or the deadline passed (reconnect() before the next; lastState() is
  // "" then), kInvalidArgument otherwise; the message has the SQLSTATE and the database's
  // words.
  common::Result<PgResult> exec(std::string_view sql, const std::vector<PgParam>& params = {},
                                std::optional<std::chrono::milliseconds> deadline = std::nullopt);
  // The SQLSTATE of the last failed exec() ("" when it did not come from the database).
  const std::string& lastState() const { return last_state_; }
  // Whether the connection is up; reconnect() opens it again (after a database restart, or a
  // deadline), first ending the backend of a statement abandoned at its deadline.
  bool connected() const;
  common::Status reconnect();
  const PgOptions& options() const { return options_; }
  // Statements abandoned at their deadline since connect().
  uint64_t abandoned() const { return abandoned_count_; }
  // Statements sent since connect() (any thread may read it).
  uint64_t statements() const { return statements_.load(std::memory_order_relaxed); }
  // The URL without its password, for logs.
  const std::string& redactedUrl() const { return redacted_; }

 private:
  PgConnection(pg_conn* conn, std::string url, PgOptions options, std::string name);
  // Waits until libpq has a whole result to give.
  enum class Wait { kReady, kTimedOut, kFailed };
  Wait awaitResult(std::chrono::steady_clock::time_point until);
  void abandon();
  // Ends the backends of abandoned statements (pg_terminate_backend, waited for).
  common::Status endAbandoned();
  pg_conn* conn_ = nullptr;
  std::string url_, redacted_;
  PgOptions options_;
  std::string name_;  // application_name: unique, so an abandoned backend is found by it
  std::string last_state_;
  struct Abandoned {
    int pid = 0;
    std::string name;
  };
  std::vector<Abandoned> abandoned_;
  std::string avoid_;  // host:port of the last abandoned statement: tried last on reconnect
  uint64_t abandoned_count_ = 0;
  std::atomic<uint64_t> statements_{0};
};

// `url` with any password replaced by "***" (postgresql://user:***@host/db, password=***).
std::string redactPassword(const std::string& url);

}  // namespace stereomap::cluster
