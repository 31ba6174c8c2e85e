#include "server/cluster/pg.hpp"

#include <libpq-fe.h>
#include <poll.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <regex>
#include <utility>

namespace stereomap::cluster {

PgParam::PgParam(double number) {
  char text[64];
  std::snprintf(text, sizeof(text), "%.17g", number);
  value = text;
}

PgParam PgParam::bytes(std::string_view data) {
  PgParam param{std::string(data)};
  param.binary = true;
  return param;
}

PgParam PgParam::null() {
  PgParam param{""};
  param.value.reset();
  return param;
}

PgResult::PgResult(pg_result* result) : result_(result) {}
PgResult::~PgResult() {
  if (result_ != nullptr) PQclear(result_);
}
PgResult::PgResult(PgResult&& other) noexcept : result_(std::exchange(other.result_, nullptr)) {}
PgResult& PgResult::operator=(PgResult&& other) noexcept {
  if (this != &other) {
    if (result_ != nullptr) PQclear(result_);
    result_ = std::exchange(other.result_, nullptr);
  }
  return *this;
}

int PgResult::rows() const { return PQntuples(result_); }
int PgResult::columns() const { return PQnfields(result_); }
bool PgResult::isNull(int row, int column) const { return PQgetisnull(result_, row, column) != 0; }
std::string PgResult::text(int row, int column) const {
  return {PQgetvalue(result_, row, column), static_cast<size_t>(PQgetlength(result_, row, column))};
}
int64_t PgResult::integer(int row, int column) const {
  return isNull(row, column) ? 0 : std::strtoll(PQgetvalue(result_, row, column), nullptr, 10);
}
double PgResult::real(int row, int column) const {
  return isNull(row, column) ? 0.0 : std::strtod(PQgetvalue(result_, row, column), nullptr);
}
std::string PgResult::bytes(int row, int column) const {
  if (isNull(row, column)) return {};
  size_t length = 0;
  unsigned char* raw = PQunescapeBytea(
      reinterpret_cast<const unsigned char*>(PQgetvalue(result_, row, column)), &length);
  if (raw == nullptr) return {};
  std::string out(reinterpret_cast<const char*>(raw), length);
  PQfreemem(raw);
  return out;
}
uint64_t PgResult::affected() const {
  const char* count = PQcmdTuples(result_);
  return count == nullptr || *count == '\0' ? 0 : std::strtoull(count, nullptr, 10);
}

std::string redactPassword(const std::string& url) {
  static const std::regex in_url(R"(^(postgres(?:ql)?://[^:/@]*):[^/]*@)");
  static const std::regex in_keywords(R"((password\s*=\s*)('[^']*'|\S+))");
  std::string out = std::regex_replace(url, in_url, "$1:***@");
  return std::regex_replace(out, in_keywords, "$1***");
}

namespace {

// libpq's messages span lines ("...failed: Connection refused\n\tIs the server running...");
// logs want one.
std::string oneLine(std::string text) {
  std::string out;
  bool space = false;
  for (char c : text) {
    if (c == '\n' || c == '\t' || c == '\r' || c == ' ') {
      space = !out.empty();
      continue;
    }
    if (space) out += ' ';
    space = false;
    out += c;
  }
  return out;
}

// A name no other connection has: "stereomap-<pid>-<random>".
std::string uniqueName() {
  static std::atomic<uint64_t> counter{0};
  static const uint64_t salt = std::random_device()();
  char name[64];
  std::snprintf(name, sizeof(name), "stereomap-%d-%llx", static_cast<int>(::getpid()),
                static_cast<unsigned long long>((salt << 20) ^ ++counter));
  return name;
}

// The URL's hosts (and ports) with `avoid` ("host:port") moved last: after a statement was
// abandoned on a database that hangs, libpq tries the others first rather than spending its
// connect timeout on that one every time (a primary that hung is failed over to another
// host). Empty strings when the URL names one host, or `avoid` is not among them.
std::pair<std::string, std::string> hostsAvoiding(const std::string& url,
                                                  const std::string& avoid) {
  if (avoid.empty()) return {};
  char* error = nullptr;
  PQconninfoOption* parsed = PQconninfoParse(url.c_str(), &error);
  if (error != nullptr) PQfreemem(error);
  if (parsed == nullptr) return {};
  std::string hosts, ports;
  for (PQconninfoOption* option = parsed; option->keyword != nullptr; ++option) {
    if (option->val == nullptr) continue;
    if (std::string_view(option->keyword) == "host") hosts = option->val;
    if (std::string_view(option->keyword) == "port") ports = option->val;
  }
  PQconninfoFree(parsed);
  const auto split = [](const std::string& list) {
    std::vector<std::string> items;
    for (size_t at = 0;;) {
      const size_t comma = list.find(',', at);
      items.push_back(list.substr(at, comma - at));
      if (comma == std::string::npos) return items;
      at = comma + 1;
    }
  };
  std::vector<std::string> host_list = split(hosts), port_list = split(ports);
  if (host_list.size() < 2) return {};
  port_list.resize(host_list.size(), port_list.size() == 1 ? port_list[0] : "5432");
  std::vector<size_t> order;
  for (size_t i = 0; i < host_list.size(); ++i) {
    if (host_list[i] + ":" + port_list[i] != avoid) order.push_back(i);
  }
  if (order.size() == host_list.size()) return {};
  for (size_t i = 0; i < host_list.size(); ++i) {
    if (host_list[i] + ":" + port_list[i] == avoid) order.push_back(i);
  }
  std::string new_hosts, new_ports;
  for (size_t i : order) {
    new_hosts += (new_hosts.empty() ? "" : ",") + host_list[i];
    new_ports += (new_ports.empty() ? "" : ",") + port_list[i];
  }
  return {new_hosts, new_ports};
}

pg_conn* open(const std::string& url, const PgOptions& options, const std::string& name,
              const std::string& avoid = "") {
  const std::string seconds =
      std::to_string(std::max<int64_t>(2, (options.connect_timeout.count() + 999) / 1000));
  // The server gives up a little after the client would: the client's deadline decides, the
  // server's timeout only frees the backend of a statement nobody waits for any more.
  const std::string server_options =
      "-c statement_timeout=" + std::to_string(options.deadline.count() + 1000) +
      " -c lock_timeout=" + std::to_string(options.lock_timeout.count()) +
      " -c idle_in_transaction_session_timeout=" +
      std::to_string(std::max<int64_t>(5000, options.deadline.count() * 2));
  // Unacknowledged bytes on a cut link end the connection within the deadline, not the
  // kernel's 15 minutes.
  const std::string user_timeout = std::to_string(options.deadline.count());
  // The URL first (expanded), then what we add: timeouts, and keepalives so that a database
  // gone silent (its machine cut off) is noticed in seconds, not hours.
  std::vector<const char*> keys = {"dbname",
                                   "connect_timeout",
                                   "keepalives",
                                   "keepalives_idle",
                                   "keepalives_interval",
                                   "keepalives_count",
                                   "tcp_user_timeout",
                                   "options",
                                   "application_name"};
  std::vector<const char*> values = {
      url.c_str(),          seconds.c_str(),        "1",         "5", "2", "3",
      user_timeout.c_str(), server_options.c_str(), name.c_str()};
  // Later keys override what the expanded URL said.
  const auto [hosts, ports] = hostsAvoiding(url, avoid);
  if (!hosts.empty()) {
    keys.insert(keys.end(), {"host", "port"});
    values.insert(values.end(), {hosts.c_str(), ports.c_str()});
  }
  keys.push_back(nullptr);
  values.push_back(nullptr);
  pg_conn* conn = PQconnectdbParams(keys.data(), values.data(), /*expand_dbname=*/1);
  if (conn != nullptr) {
    // The database's notices ("relation already exists, skipping") are not for our logs.
    PQsetNoticeProcessor(
        conn, [](void*, const char*) {}, nullptr);
    // Sending never blocks either: a large statement is flushed under the deadline's poll.
    if (PQstatus(conn) == CONNECTION_OK) PQsetnonblocking(conn, 1);
  }
  return conn;
}

}  // namespace

common::Result<std::unique_ptr<PgConnection>> PgConnection::connect(const std::string& url,
                                                                    const PgOptions& options) {
  std::string name = uniqueName();
  pg_conn* conn = open(url, options, name);
  if (conn == nullptr)
    return common::makeError(common::ErrorCode::kUnavailable, "libpq: out of memory");
  if (PQstatus(conn) != CONNECTION_OK) {
    const std::string why = oneLine(PQerrorMessage(conn));
    PQfinish(conn);
    const bool refused_credentials = why.find("authentication") != std::string::npos ||
                                     why.find("password") != std::string::npos;
    return common::makeError(
        refused_credentials ? common::ErrorCode::kInvalidArgument : common::ErrorCode::kUnavailable,
        "PostgreSQL at " + redactPassword(url) +
            (refused_credentials ? " refused the credentials: " : " cannot be reached: ") + why);
  }
  return std::unique_ptr<PgConnection>(new PgConnection(conn, url, options, std::move(name)));
}

PgConnection::PgConnection(pg_conn* conn, std::string url, PgOptions options, std::string name)
    : conn_(conn),
      url_(std::move(url)),
      redacted_(redactPassword(url_)),
      options_(options),
      name_(std::move(name)) {}

PgConnection::~PgConnection() {
  if (conn_ != nullptr) PQfinish(conn_);
}

bool PgConnection::connected() const {
  return conn_ != nullptr && PQstatus(conn_) == CONNECTION_OK;
}

common::Status PgConnection::reconnect() {
  if (conn_ != nullptr) PQfinish(conn_);
  name_ = uniqueName();
  conn_ = open(url_, options_, name_, avoid_);
  if (!connected()) {
    const std::string why = oneLine(conn_ != nullptr ? PQerrorMessage(conn_) : "out of memory");
    return common::makeError(common::ErrorCode::kUnavailable,
                             "PostgreSQL at " + redacted_ + " cannot be reached: " + why);
  }
  return endAbandoned();
}

common::Status PgConnection::endAbandoned() {
  while (!abandoned_.empty()) {
    const Abandoned old = abandoned_.back();  // a copy: exec() may add to the list
    // Waits (up to the deadline) until the backend has exited: whatever it had under way is
    // then committed or rolled back for good, and the caller's next statement sees which. A
    // database restarted meanwhile has no such backend (the name tells it from a reused pid).
    auto ended = exec(
        "SELECT pg_terminate_backend(pid, $3) FROM pg_stat_activity "
        "WHERE pid = $1 AND application_name = $2",
        {old.pid, old.name, static_cast<int64_t>(options_.deadline.count())});
    if (!ended) {
      return common::makeError(common::ErrorCode::kUnavailable,
                               "cannot end the statement abandoned at its deadline (backend " +
                                   std::to_string(old.pid) + "): " + ended.error().message);
    }
    if (ended->rows() == 1 && ended->text(0, 0) != "t") {
      if (conn_ != nullptr) PQfinish(conn_);
      conn_ = nullptr;
      return common::makeError(common::ErrorCode::kUnavailable,
                               "the statement abandoned at its deadline (backend " +
                                   std::to_string(old.pid) + ") has not ended yet");
    }
    abandoned_.pop_back();
  }
  return common::Ok{};
}

void PgConnection::abandon() {
  if (conn_ == nullptr) return;
  // No PQcancel: it waits for the postmaster's answer, without a bound, and a hung database
  // gives none. The backend is ended from the next connection instead.
  const int pid = PQbackendPID(conn_);
  if (pid != 0) abandoned_.push_back({pid, name_});
  if (const char* host = PQhost(conn_); host != nullptr) {
    avoid_ = std::string(host) + ":" + PQport(conn_);
  }
  ++abandoned_count_;
  PQfinish(conn_);
  conn_ = nullptr;
}

PgConnection::Wait PgConnection::awaitResult(std::chrono::steady_clock::time_point until) {
  for (;;) {
    const int flushed = PQflush(conn_);  // 0: all sent, 1: more to send, -1: failed
    if (flushed < 0) return Wait::kFailed;
    if (flushed == 0) {
      if (PQconsumeInput(conn_) == 0) return Wait::kFailed;
      if (PQisBusy(conn_) == 0) return Wait::kReady;
    }
    const auto now = std::chrono::steady_clock::now();
    if (now >= until) return Wait::kTimedOut;
    // Rounded up: a wait of less than a millisecond is a wait, not a timeout.
    const auto left = std::chrono::ceil<std::chrono::milliseconds>(until - now);
    pollfd fd{PQsocket(conn_), static_cast<short>(POLLIN | (flushed == 1 ? POLLOUT : 0)), 0};
    const int ready = ::poll(&fd, 1, static_cast<int>(std::min<int64_t>(left.count(), 1 << 30)));
    if (ready < 0 && errno != EINTR) return Wait::kFailed;
    if (ready > 0 && (fd.revents & POLLIN) != 0 && PQconsumeInput(conn_) == 0) {
      return Wait::kFailed;
    }
  }
}

common::Result<PgResult> PgConnection::exec(std::string_view sql,
                                            const std::vector<PgParam>& params,
                                            std::optional<std::chrono::milliseconds> deadline) {
  last_state_.clear();
  if (!connected()) {
    return common::makeError(common::ErrorCode::kUnavailable,
                             "the connection to PostgreSQL at " + redacted_ + " is down");
  }
  const auto budget = deadline.value_or(options_.deadline);
  const auto until = std::chrono::steady_clock::now() + budget;
  std::vector<const char*> values;
  std::vector<int> lengths, formats;
  values.reserve(params.size());
  for (const auto& param : params) {
    values.push_back(param.value ? param.value->data() : nullptr);
    lengths.push_back(param.value ? static_cast<int>(param.value->size()) : 0);
    formats.push_back(param.binary ? 1 : 0);
  }
  const std::string statement(sql);
  const auto lost = [&](const std::string& what) -> common::Error {
    std::string why = oneLine(conn_ != nullptr ? PQerrorMessage(conn_) : "");
    if (why.empty()) why = "connection lost";
    return common::makeError(common::ErrorCode::kUnavailable,
                             "PostgreSQL at " + redacted_ + ": " + what + ": " + why);
  };
  statements_.fetch_add(1, std::memory_order_relaxed);
  if (PQsendQueryParams(conn_, statement.c_str(), static_cast<int>(params.size()), nullptr,
                        values.data(), lengths.data(), formats.data(), /*text=*/0) == 0) {
    return lost("cannot send the statement");
  }
  // The statement's results; the last one (or its first error) is the answer.
  std::optional<PgResult> answer;
  for (;;) {
    const Wait waited = awaitResult(until);
    if (waited == Wait::kFailed) {
      auto error = lost("the connection failed during a statement");
      abandon();  // whether it ran is unknown: its backend, if any, is ended first
      return error;
    }
    if (waited == Wait::kTimedOut) {
      abandon();
      return common::makeError(common::ErrorCode::kUnavailable,
                               "PostgreSQL at " + redacted_ + " did not answer within " +
                                   std::to_string(budget.count()) +
                                   " ms (the statement was abandoned)");
    }
    pg_result* raw = PQgetResult(conn_);
    if (raw == nullptr) break;
    PgResult result(raw);
    const ExecStatusType status = PQresultStatus(raw);
    const bool failed = status != PGRES_COMMAND_OK && status != PGRES_TUPLES_OK;
    if (!answer || (failed && PQresultStatus(answer->raw()) != PGRES_FATAL_ERROR)) {
      answer = std::move(result);
    }
  }
  if (!answer) return lost("no answer to the statement");
  pg_result* raw = answer->raw();
  const ExecStatusType status = PQresultStatus(raw);
  if (status == PGRES_COMMAND_OK || status == PGRES_TUPLES_OK) return std::move(*answer);

  const char* state = PQresultErrorField(raw, PG_DIAG_SQLSTATE);
  last_state_ = state != nullptr ? state : "";
  const char* primary = PQresultErrorField(raw, PG_DIAG_MESSAGE_PRIMARY);
  const std::string why = oneLine(primary != nullptr ? primary : PQerrorMessage(conn_));
  common::ErrorCode code = common::ErrorCode::kInvalidArgument;
  if (!connected() || last_state_.rfind("08", 0) == 0 || last_state_.rfind("57P", 0) == 0) {
    code = common::ErrorCode::kUnavailable;  // connection exceptions, an operator's shutdown
  } else if (last_state_ == "57014" || last_state_ == "55P03") {
    code = common::ErrorCode::kUnavailable;  // the server's statement or lock timeout
  } else if (last_state_ == kFencedState || last_state_ == kUniqueViolationState ||
             last_state_ == "40001" || last_state_ == "40P01") {
    code = common::ErrorCode::kConflict;  // fenced, unique violation, serialization, deadlock
  }
  return common::makeError(
      code, "PostgreSQL" + (last_state_.empty() ? std::string() : " " + last_state_) + ": " + why);
}

}  // namespace stereomap::cluster
