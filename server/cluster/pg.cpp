#include "server/cluster/pg.hpp"

#include <libpq-fe.h>

#include <cstdio>
#include <cstdlib>
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

pg_conn* open(const std::string& url, std::chrono::seconds timeout) {
  const std::string seconds = std::to_string(std::max<int64_t>(1, timeout.count()));
  // The URL first (expanded), then what we add: a connect timeout, and keepalives so that a
  // database gone silent (its machine cut off) is noticed in seconds, not hours.
  const char* keys[] = {"dbname",
                        "connect_timeout",
                        "keepalives",
                        "keepalives_idle",
                        "keepalives_interval",
                        "keepalives_count",
                        "application_name",
                        nullptr};
  const char* values[] = {url.c_str(), seconds.c_str(), "1", "5", "2", "3", "stereomap", nullptr};
  pg_conn* conn = PQconnectdbParams(keys, values, /*expand_dbname=*/1);
  // The database's notices ("relation already exists, skipping") are not for our logs.
  if (conn != nullptr)
    PQsetNoticeProcessor(
        conn, [](void*, const char*) {}, nullptr);
  return conn;
}

}  // namespace

common::Result<std::unique_ptr<PgConnection>> PgConnection::connect(const std::string& url,
                                                                    std::chrono::seconds timeout) {
  pg_conn* conn = open(url, timeout);
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
  return std::unique_ptr<PgConnection>(new PgConnection(conn, url, timeout));
}

PgConnection::PgConnection(pg_conn* conn, std::string url, std::chrono::seconds timeout)
    : conn_(conn), url_(std::move(url)), redacted_(redactPassword(url_)), timeout_(timeout) {}

PgConnection::~PgConnection() {
  if (conn_ != nullptr) PQfinish(conn_);
}

bool PgConnection::connected() const {
  return conn_ != nullptr && PQstatus(conn_) == CONNECTION_OK;
}

common::Status PgConnection::reconnect() {
  if (conn_ != nullptr) PQfinish(conn_);
  conn_ = open(url_, timeout_);
  if (connected()) return common::Ok{};
  const std::string why = oneLine(conn_ != nullptr ? PQerrorMessage(conn_) : "out of memory");
  return common::makeError(common::ErrorCode::kUnavailable,
                           "PostgreSQL at " + redacted_ + " cannot be reached: " + why);
}

common::Result<PgResult> PgConnection::exec(std::string_view sql,
                                            const std::vector<PgParam>& params) {
  last_state_.clear();
  if (!connected()) {
    return common::makeError(common::ErrorCode::kUnavailable,
                             "the connection to PostgreSQL at " + redacted_ + " is down");
  }
  std::vector<const char*> values;
  std::vector<int> lengths, formats;
  values.reserve(params.size());
  for (const auto& param : params) {
    values.push_back(param.value ? param.value->data() : nullptr);
    lengths.push_back(param.value ? static_cast<int>(param.value->size()) : 0);
    formats.push_back(param.binary ? 1 : 0);
  }
  const std::string statement(sql);
  pg_result* raw = PQexecParams(conn_, statement.c_str(), static_cast<int>(params.size()), nullptr,
                                values.data(), lengths.data(), formats.data(), /*text=*/0);
  PgResult result(raw);
  const ExecStatusType status = raw != nullptr ? PQresultStatus(raw) : PGRES_FATAL_ERROR;
  if (status == PGRES_COMMAND_OK || status == PGRES_TUPLES_OK) return result;

  const char* state = raw != nullptr ? PQresultErrorField(raw, PG_DIAG_SQLSTATE) : nullptr;
  last_state_ = state != nullptr ? state : "";
  const char* primary = raw != nullptr ? PQresultErrorField(raw, PG_DIAG_MESSAGE_PRIMARY) : nullptr;
  const std::string why = oneLine(primary != nullptr ? primary : PQerrorMessage(conn_));
  common::ErrorCode code = common::ErrorCode::kInvalidArgument;
  if (!connected() || last_state_.rfind("08", 0) == 0 || last_state_.rfind("57P", 0) == 0) {
    code = common::ErrorCode::kUnavailable;  // connection exceptions, an operator's shutdown
  } else if (last_state_ == kFencedState || last_state_ == "23505" || last_state_ == "40001" ||
             last_state_ == "40P01") {
    code = common::ErrorCode::kConflict;  // fenced, unique violation, serialization, deadlock
  }
  return common::makeError(
      code, "PostgreSQL" + (last_state_.empty() ? std::string() : " " + last_state_) + ": " + why);
}

}  // namespace stereomap::cluster
