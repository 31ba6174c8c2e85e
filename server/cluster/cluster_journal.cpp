#include "server/cluster/cluster_journal.hpp"

#include <spdlog/spdlog.h>

#include <algorithm>

#include "common/time.hpp"
#include "server/cluster/snapshot_codec.hpp"
#include "server/core/session_json.hpp"

namespace stereomap::cluster {

using common::ErrorCode;
using common::makeError;
namespace journal = proto::journal;

namespace {

// The kind column: what a row holds, so that frames can be read without the rest.
// A vehicle's frame alignment is a correction too: like a pose graph's, it moves frames already
// fused, so no snapshot older than it may be used (recovery and compaction go by kind 4).
enum Kind : int { kCloud = 1, kPose = 2, kEvent = 3, kCorrection = 4 };

// A group's bounds: PostgreSQL takes at most 65535 parameters (6 per row), and a group
// should not hold a commit up for long.
constexpr size_t kMaxGroupRows = 2000;
constexpr size_t kMaxGroupBytes = 32u << 20;
constexpr int kFramesPerRead = 64;
constexpr size_t kParamsPerRow = 6;
// A page of records read for recovery or an export: at most this many rows and (but for a
// first row larger than it) bytes, so that memory stays bounded whatever the clouds' size.
constexpr int kRowsPerPage = 1024;
constexpr int64_t kBytesPerPage = 8 << 20;

// A cloud's record without its payload: what recovery needs of a frame a snapshot holds.
std::vector<uint8_t> withoutPayload(const proto::CloudFrameMsg& frame) {
  proto::CloudFrameMsg meta = frame;
  std::vector<uint8_t>().swap(meta.payload);
  return journal::encodeRecord(meta);
}

}  // namespace

void JournalRows::add(const std::string& session, uint64_t number, int64_t epoch, int kind,
                      const std::vector<uint8_t>& record,
                      const std::optional<std::vector<uint8_t>>& meta) {
  const auto bytes = [](const std::vector<uint8_t>& data) {
    return PgParam::bytes(
        std::string_view(reinterpret_cast<const char*>(data.data()), data.size()));
  };
  params_.emplace_back(session);
  params_.emplace_back(number);
  params_.emplace_back(epoch);
  params_.emplace_back(kind);
  params_.push_back(bytes(record));
  params_.push_back(meta ? bytes(*meta) : PgParam::null());
  bytes_ += record.size();
  ++rows_;
}

void JournalRows::add(const std::string& session, uint64_t number, int64_t epoch,
                      const journal::JournalRecord& record) {
  const int kind = std::visit(
      [](const auto& m) -> int {
        using Message = std::decay_t<decltype(m)>;
        if constexpr (std::is_same_v<Message, proto::CloudFrameMsg>) return kCloud;
        if constexpr (std::is_same_v<Message, proto::PoseMsg>) return kPose;
        if constexpr (std::is_same_v<Message, proto::SessionEventMsg>) return kEvent;
        return kCorrection;
      },
      record);
  const auto* frame = std::get_if<proto::CloudFrameMsg>(&record);
  add(session, number, epoch, kind, journal::encodeRecord(record),
      frame != nullptr ? std::optional(withoutPayload(*frame)) : std::nullopt);
}

bool JournalRows::full() const { return rows_ >= kMaxGroupRows || bytes_ >= kMaxGroupBytes; }

std::string JournalRows::statement() const {
  std::string sql = "INSERT INTO sm_journal (session, number, epoch, kind, record, meta) VALUES ";
  for (size_t i = 0; i < rows_; ++i) {
    const size_t p = i * kParamsPerRow;
    if (i > 0) sql += ',';
    for (size_t k = 1; k <= kParamsPerRow; ++k) {
      sql += k == 1 ? "($" : ",$";
      sql += std::to_string(p + k);
    }
    sql += ')';
  }
  return sql;
}

void JournalRows::clear() {
  params_.clear();
  rows_ = bytes_ = 0;
}

PgOptions ClusterJournal::readerOptions() {
  // Pages of records (8 MB) and compressed snapshots (tens of MB) take longer than a group.
  return {.connect_timeout = std::chrono::seconds(2), .deadline = std::chrono::seconds(30)};
}

struct ClusterJournal::Pending {
  std::string session;
  int kind = 0;
  std::vector<uint8_t> record;
  std::optional<std::vector<uint8_t>> meta;  // a cloud's record without its payload
  int64_t enqueued_ns = 0;
  int64_t epoch = 0;
  uint64_t number = 0;
  bool done = false;
  std::optional<common::Error> error;
};

common::Result<std::unique_ptr<ClusterJournal>> ClusterJournal::open(const std::string& url) {
  // A group of samples commits in milliseconds (a WAL flush): three seconds is a database in
  // trouble, and its samples are refused (their vehicles keep them) rather than held.
  auto writer = PgConnection::connect(
      url, {.connect_timeout = std::chrono::seconds(2), .deadline = std::chrono::seconds(3)});
  if (!writer) return writer.error();
  // Reads of a page of records and writes of a compressed snapshot (tens of MB) take longer.
  auto reader = PgConnection::connect(url, readerOptions());
  if (!reader) return reader.error();
  return std::unique_ptr<ClusterJournal>(
      new ClusterJournal(std::move(*writer), std::move(*reader), url));
}

ClusterJournal::ClusterJournal(std::unique_ptr<PgConnection> writer,
                               std::unique_ptr<PgConnection> reader, std::string url)
    : url_(std::move(url)), writer_(std::move(writer)), reader_(std::move(reader)) {
  latencies_.reserve(kLatencyWindow);
  committer_ = std::thread([this] { commitLoop(); });
}

ClusterJournal::~ClusterJournal() {
  {
    std::lock_guard lock(mutex_);
    stop_ = true;
  }
  wake_.notify_all();
  committer_.join();
}

void ClusterJournal::adopt(const std::string& session, int64_t epoch, uint64_t last_number) {
  std::lock_guard lock(mutex_);
  owned_[session] = {epoch, last_number + 1};
}

void ClusterJournal::drop(const std::string& session) {
  std::lock_guard lock(mutex_);
  owned_.erase(session);
}

std::optional<int64_t> ClusterJournal::epochOf(const std::string& session) const {
  std::lock_guard lock(mutex_);
  const auto it = owned_.find(session);
  if (it == owned_.end()) return std::nullopt;
  return it->second.epoch;
}

void ClusterJournal::onFenced(FencedCallback callback) {
  std::lock_guard lock(mutex_);
  on_fenced_ = std::move(callback);
}

common::Result<uint64_t> ClusterJournal::append(const proto::CloudFrameMsg& frame) {
  return appendRecord(frame.session_id, kCloud, frame, withoutPayload(frame));
}
common::Result<uint64_t> ClusterJournal::append(const proto::PoseMsg& pose) {
  return appendRecord(pose.session_id, kPose, pose);
}
common::Result<uint64_t> ClusterJournal::append(const proto::SessionEventMsg& event) {
  return appendRecord(event.session_id, kEvent, event);
}
common::Result<uint64_t> ClusterJournal::append(const proto::PoseCorrectionMsg& correction) {
  return appendRecord(correction.session_id, kCorrection, correction);
}

common::Result<uint64_t> ClusterJournal::append(const proto::FrameAlignmentMsg& alignment) {
  return appendRecord(alignment.session_id, kCorrection, alignment);
}

common::Result<uint64_t> ClusterJournal::appendRecord(const std::string& session, int kind,
                                                      const journal::JournalRecord& record,
                                                      std::optional<std::vector<uint8_t>> meta) {
  Pending pending{session, kind, journal::encodeRecord(record), std::move(meta), common::nowNs()};
  std::unique_lock lock(mutex_);
  if (!owned_.contains(session)) {
    return makeError(ErrorCode::kConflict,
                     "session '" + session + "' is not this server's to write");
  }
  waiting_.push_back(&pending);
  wake_.notify_one();
  done_.wait(lock, [&] { return pending.done; });
  if (pending.error) return *pending.error;
  return pending.number;
}

void ClusterJournal::commitLoop() {
  std::vector<Pending*> group;
  for (;;) {
    std::unique_lock lock(mutex_);
    wake_.wait(lock, [&] { return stop_ || !waiting_.empty(); });
    if (waiting_.empty()) return;  // stopping, and nobody waits
    group.clear();
    size_t bytes = 0;
    while (!waiting_.empty() && group.size() < kMaxGroupRows &&
           (group.empty() || bytes + waiting_.front()->record.size() <= kMaxGroupBytes)) {
      Pending* next = waiting_.front();
      waiting_.pop_front();
      bytes += next->record.size();
      const auto owned = owned_.find(next->session);
      if (owned == owned_.end()) {  // dropped while it waited
        next->error = makeError(ErrorCode::kConflict,
                                "session '" + next->session + "' is not this server's to write");
        next->done = true;
        continue;
      }
      next->epoch = owned->second.epoch;
      next->number = owned->second.next_number++;
      group.push_back(next);
    }
    lock.unlock();
    if (!group.empty()) commitGroup(group);
    lock.lock();
    done_.notify_all();
  }
}

common::Status ClusterJournal::insertRows(std::vector<Pending*>& rows, std::string* state) {
  state->clear();
  if (!writer_->connected()) {
    // A database known to be down refuses at once, so that samples arriving meanwhile are not
    // each held for a connect timeout.
    const auto now = std::chrono::steady_clock::now();
    if (now < retry_connect_at_) {
      return makeError(ErrorCode::kUnavailable,
                       "the cluster's database is unreachable: " + unreachable_why_);
    }
    if (auto reconnected = writer_->reconnect(); !reconnected) {
      retry_connect_at_ = now + std::chrono::milliseconds(500);
      unreachable_why_ = reconnected.error().message;
      return reconnected.error();
    }
  }
  // Rows of an earlier group that may have committed unacknowledged: gone before these.
  std::map<std::string, std::pair<int64_t, uint64_t>> doubts;  // session -> (epoch, from)
  {
    std::lock_guard lock(mutex_);
    for (const Pending* row : rows) {
      const auto owned = owned_.find(row->session);
      if (owned != owned_.end() && owned->second.doubt_from != 0 &&
          owned->second.epoch == row->epoch) {
        doubts[row->session] = {row->epoch, owned->second.doubt_from};
      }
    }
  }
  JournalRows batch;
  for (const Pending* row : rows) {
    batch.add(row->session, row->number, row->epoch, row->kind, row->record, row->meta);
  }
  const std::string sql = batch.statement();
  const std::vector<PgParam>& params = batch.params();
  if (doubts.empty()) {
    auto inserted = writer_->exec(sql, params);
    if (!inserted) {
      *state = writer_->lastState();
      return inserted.error();
    }
    return common::Ok{};
  }
  // One transaction: if this one's answer is lost too, the doubt stays as it was. A fenced
  // session's INSERT fails, and its DELETE is rolled back with it: the rows may be the new
  // owner's to keep (it read them when it took the session).
  auto transaction = [&]() -> common::Status {
    if (auto begun = writer_->exec("BEGIN"); !begun) return begun.error();
    for (const auto& [session, doubt] : doubts) {
      auto deleted =
          writer_->exec("DELETE FROM sm_journal WHERE session = $1 AND epoch = $2 AND number >= $3",
                        {session, doubt.first, doubt.second});
      if (!deleted) return deleted.error();
      if (deleted->affected() > 0) {
        spdlog::warn(
            "session '{}': {} journal rows from {} on were committed without an answer (the "
            "connection was lost) and never acknowledged; deleted before writing again",
            session, deleted->affected(), doubt.second);
      }
    }
    if (auto inserted = writer_->exec(sql, params); !inserted) return inserted.error();
    if (auto committed = writer_->exec("COMMIT"); !committed) return committed.error();
    return common::Ok{};
  };
  auto written = transaction();
  if (!written) {
    *state = writer_->lastState();  // before ROLLBACK's answer replaces it
    if (writer_->connected()) (void)writer_->exec("ROLLBACK");
    return written;
  }
  std::lock_guard lock(mutex_);
  for (const auto& [session, doubt] : doubts) {
    const auto owned = owned_.find(session);
    if (owned != owned_.end() && owned->second.epoch == doubt.first) owned->second.doubt_from = 0;
  }
  return common::Ok{};
}

void ClusterJournal::commitGroup(std::vector<Pending*>& group) {
  std::string state;
  auto committed = insertRows(group, &state);
  std::vector<std::pair<std::string, std::string>> fenced;
  // A stale epoch, or a row another writer holds at a number this process gave: either way
  // the session is another's now. Never a reason to delete rows (they are that writer's).
  const auto another_writer = [](const std::string& sqlstate) {
    return sqlstate == kFencedState || sqlstate == kUniqueViolationState;
  };
  if (!committed && another_writer(state)) {
    // One session refused the whole group: each session again on its own, so that the others
    // commit.
    std::map<std::string, std::vector<Pending*>> by_session;
    for (Pending* p : group) by_session[p->session].push_back(p);
    for (auto& [session, rows] : by_session) {
      auto alone = insertRows(rows, &state);
      const bool stale = !alone && another_writer(state);
      if (stale) fenced.emplace_back(session, alone.error().message);
      for (Pending* p : rows) {
        if (!alone) {
          p->error = stale ? makeError(ErrorCode::kConflict, "session '" + session +
                                                                 "' was fenced: another server "
                                                                 "owns it now (" +
                                                                 alone.error().message + ")")
                           : alone.error();
        }
      }
    }
  } else if (!committed) {
    for (Pending* p : group) p->error = committed.error();
  }

  const int64_t now = common::nowNs();
  FencedCallback callback;
  {
    std::lock_guard lock(mutex_);
    for (Pending* p : group) {
      if (p->error) {
        // Numbers are given back: nothing numbered after them was written meanwhile (this
        // thread alone numbers rows), so the journal keeps no gap. Whether the failed
        // statement committed may be unknown (its answer lost with the connection, or
        // abandoned at its deadline): its rows are in doubt until the session's next write
        // deletes them. They carry this adoption's epoch, which no other process writes at,
        // and were never acknowledged.
        if (auto owned = owned_.find(p->session);
            owned != owned_.end() && owned->second.epoch == p->epoch) {
          owned->second.next_number = std::min(owned->second.next_number, p->number);
          owned->second.doubt_from = owned->second.doubt_from == 0
                                         ? p->number
                                         : std::min(owned->second.doubt_from, p->number);
        }
      } else {
        const double seconds = static_cast<double>(now - p->enqueued_ns) * 1e-9;
        if (latencies_.size() < kLatencyWindow) {
          latencies_.push_back(seconds);
        } else {
          latencies_[latency_next_] = seconds;
        }
        latency_next_ = (latency_next_ + 1) % kLatencyWindow;
        ++committed_;
      }
      p->done = true;
    }
    if (committed) ++groups_;
    for (const auto& [session, why] : fenced) owned_.erase(session);
    callback = on_fenced_;
  }
  for (const auto& [session, why] : fenced) {
    spdlog::error("session '{}': fenced by the cluster's database ({}); unloading it", session,
                  why);
    if (callback) callback(session, why);
  }
}

std::vector<double> ClusterJournal::commitLatencies() const {
  std::lock_guard lock(mutex_);
  return latencies_;
}
uint64_t ClusterJournal::committedSamples() const {
  std::lock_guard lock(mutex_);
  return committed_;
}
uint64_t ClusterJournal::committedGroups() const {
  std::lock_guard lock(mutex_);
  return groups_;
}

common::Result<PgResult> ClusterJournal::readerExec(std::string_view sql,
                                                    const std::vector<PgParam>& params) const {
  std::lock_guard lock(reader_mutex_);
  if (!reader_->connected()) {
    if (auto reconnected = reader_->reconnect(); !reconnected) return reconnected.error();
  }
  auto result = reader_->exec(sql, params);
  // A connection the database lost while idle (a restart) shows only when used: once more on
  // a new one. (Reads repeat safely; a snapshot's INSERT ... ON CONFLICT too.)
  if (!result && !reader_->connected()) {
    if (auto reconnected = reader_->reconnect(); !reconnected) return reconnected.error();
    result = reader_->exec(sql, params);
  }
  return result;
}

common::Status ClusterJournal::forEachFrame(
    const std::string& session, uint64_t after, uint64_t up_to,
    const std::function<void(const proto::CloudFrameMsg& frame, uint64_t number)>& visit) const {
  for (uint64_t from = after; from < up_to;) {
    auto rows = readerExec(
        "SELECT number, record FROM sm_journal WHERE session = $1 AND kind = $2 AND number > $3 "
        "AND number <= $4 ORDER BY number LIMIT $5",
        {session, static_cast<int>(kCloud), from, up_to, kFramesPerRead});
    if (!rows) return rows.error();
    if (rows->rows() == 0) break;
    for (int i = 0; i < rows->rows(); ++i) {
      const auto number = static_cast<uint64_t>(rows->integer(i, 0));
      const std::string bytes = rows->bytes(i, 1);
      auto record =
          journal::decodeRecord(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size());
      if (record && std::holds_alternative<proto::CloudFrameMsg>(*record)) {
        visit(std::get<proto::CloudFrameMsg>(*record), number);
      }
      from = number;
    }
  }
  return common::Ok{};
}

common::Status ClusterJournal::saveSnapshot(const std::string& session, uint64_t journal_number,
                                            const std::string& ot) {
  const auto epoch = epochOf(session);
  if (!epoch) {
    return makeError(ErrorCode::kConflict,
                     "session '" + session + "' is not this server's to write");
  }
  auto saved = readerExec(
      "INSERT INTO sm_snapshots (session, number, epoch, map) VALUES ($1, $2, $3, $4) "
      "ON CONFLICT (session, number) DO UPDATE SET map = EXCLUDED.map, epoch = EXCLUDED.epoch",
      {session, journal_number, *epoch, PgParam::bytes(packSnapshot(ot))});
  if (!saved) return saved.error();
  // Recovery starts from the newest; the one before it is kept in case the newest cannot be
  // read (the frames after it are whole in the journal).
  auto pruned = readerExec(
      "DELETE FROM sm_snapshots WHERE session = $1 AND number < (SELECT min(number) FROM ("
      "  SELECT number FROM sm_snapshots WHERE session = $1 ORDER BY number DESC LIMIT 2) kept)",
      {session});
  if (!pruned) return pruned.error();
  return common::Ok{};
}

common::Result<ClusterJournal::RecordScan> ClusterJournal::forEachRecord(
    const std::string& session,
    const std::function<void(proto::journal::JournalRecord&& record, uint64_t number)>& visit,
    uint64_t without_payloads_up_to) const {
  return scanRecords(
      session, without_payloads_up_to,
      [this](std::string_view sql, const std::vector<PgParam>& params) {
        return readerExec(sql, params);
      },
      visit);
}

common::Result<ClusterJournal::RecordScan> ClusterJournal::scanRecords(
    const std::string& session, uint64_t without_payloads_up_to, const Exec& exec,
    const std::function<void(proto::journal::JournalRecord&& record, uint64_t number)>& visit) {
  RecordScan scan;
  // A page: up to kRowsPerPage rows, cut where their bytes pass kBytesPerPage (the first row
  // always comes). Clouds up to `without_payloads_up_to` come as their meta when they have it.
  constexpr const char* kPage =
      "SELECT number, data FROM ("
      "  SELECT number, data, sum(octet_length(data)) OVER (ORDER BY number) AS running, "
      "    row_number() OVER (ORDER BY number) AS nth FROM ("
      "    SELECT number, CASE WHEN kind = 1 AND number <= $3 AND meta IS NOT NULL THEN meta "
      "      ELSE record END AS data "
      "    FROM sm_journal WHERE session = $1 AND number > $2 ORDER BY number LIMIT $4) page"
      ") sized WHERE nth = 1 OR running <= $5 ORDER BY number";
  for (uint64_t from = 0;;) {
    auto rows = exec(kPage, {session, from, without_payloads_up_to, kRowsPerPage, kBytesPerPage});
    if (!rows) return rows.error();
    if (rows->rows() == 0) return scan;
    for (int i = 0; i < rows->rows(); ++i) {
      const auto number = static_cast<uint64_t>(rows->integer(i, 0));
      from = scan.last_number = number;
      const std::string bytes = rows->bytes(i, 1);
      auto record =
          journal::decodeRecord(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size());
      if (!record) {
        ++scan.unreadable;
        continue;
      }
      visit(std::move(*record), number);
    }
  }
}

common::Result<StoredSession> ClusterJournal::read(const std::string& session) {
  // A connection of its own: recoveries run side by side, and beside the reader's exports and
  // snapshots.
  auto db = PgConnection::connect(url_, readerOptions());
  if (!db) return db.error();
  const Exec exec = [&db](std::string_view sql, const std::vector<PgParam>& params) {
    return (*db)->exec(sql, params);
  };
  StoredSession stored;
  // The newest snapshot that can be read (the one before it when it cannot).
  auto snapshots =
      exec("SELECT number, map FROM sm_snapshots WHERE session = $1 ORDER BY number DESC LIMIT 2",
           {session});
  if (!snapshots) return snapshots.error();
  for (int i = 0; i < snapshots->rows(); ++i) {
    auto ot = unpackSnapshot(snapshots->bytes(i, 1));
    if (ot) {
      stored.snapshot_number = static_cast<uint64_t>(snapshots->integer(i, 0));
      stored.snapshot = std::move(*ot);
      break;
    }
    spdlog::warn("session '{}': its snapshot of record {} cannot be read ({}){}", session,
                 snapshots->integer(i, 0), ot.error().message,
                 i + 1 < snapshots->rows() ? "; trying the one before" : "");
  }
  // The frames the snapshot holds come without their payloads (counted, never fused again).
  auto read = scanRecords(session, stored.snapshot_number, exec,
                          [&](proto::journal::JournalRecord&& record, uint64_t number) {
                            if (auto* frame = std::get_if<proto::CloudFrameMsg>(&record);
                                frame != nullptr && number <= stored.snapshot_number) {
                              std::vector<uint8_t>().swap(frame->payload);
                            }
                            stored.records.push_back(std::move(record));
                            stored.numbers.push_back(number);
                          });
  if (!read) return read.error();
  stored.last_number = read->last_number;
  stored.unreadable = read->unreadable;
  // What made it (a site, a diff), kept in its summary since it was written.
  auto summary = exec("SELECT coalesce(summary, '') FROM sm_sessions WHERE id = $1", {session});
  if (!summary) return summary.error();
  if (summary->rows() > 0) {
    stored.origin =
        core::sessionFromJson(session, nlohmann::json::parse(summary->text(0, 0), nullptr, false))
            .origin;
  }
  return stored;
}

}  // namespace stereomap::cluster
