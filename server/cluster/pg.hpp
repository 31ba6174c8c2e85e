// A PostgreSQL connection through libpq. Every statement takes its values as parameters,
// never pasted into the SQL text, so no id or payload from outside can change what a
// statement does. Results come back as text (bytea unescaped by bytes()).
//
//   auto db = PgConnection::connect("postgresql://sm@127.0.0.1:5432/stereomap");
//   auto rows = db->exec("SELECT epoch FROM sm_sessions WHERE id = $1", {session});
//   int64_t epoch = rows->integer(0, 0);
#pragma once

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
  pg_result* result_ = nullptr;
};

// The SQLSTATE the database's fencing trigger raises when a write carries a stale epoch.
inline constexpr const char* kFencedState = "SMF01";

class PgConnection {
 public:
  // Connects (a libpq URL or key=value string); the error says whether the server could not
  // be reached or refused the credentials, with libpq's words. `timeout`: for connecting.
  static common::Result<std::unique_ptr<PgConnection>> connect(
      const std::string& url, std::chrono::seconds timeout = std::chrono::seconds(5));
  ~PgConnection();
  PgConnection(const PgConnection&) = delete;
  PgConnection& operator=(const PgConnection&) = delete;

  // Runs one statement. Errors: kConflict for a fenced write (kFencedState) or a unique
  // violation, kUnavailable when the connection is lost (reconnect() before the next),
  // kInvalidArgument otherwise; the message has the SQLSTATE and the database's words.
  common::Result<PgResult> exec(std::string_view sql, const std::vector<PgParam>& params = {});
  // The SQLSTATE of the last failed exec() ("" when it did not come from the database).
  const std::string& lastState() const { return last_state_; }
  // Whether the connection is up; reconnect() opens it again (after a database restart).
  bool connected() const;
  common::Status reconnect();
  // The URL without its password, for logs.
  const std::string& redactedUrl() const { return redacted_; }

 private:
  PgConnection(pg_conn* conn, std::string url, std::chrono::seconds timeout);
  pg_conn* conn_ = nullptr;
  std::string url_, redacted_;
  std::chrono::seconds timeout_;
  std::string last_state_;
};

// `url` with any password replaced by "***" (postgresql://user:***@host/db, password=***).
std::string redactPassword(const std::string& url);

}  // namespace stereomap::cluster
