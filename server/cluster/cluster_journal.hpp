// The cluster's journal and snapshots in PostgreSQL: the MapServer's IngestLog, SnapshotSink
// and FrameArchive when the server runs with --cluster. A sample counts as received once its
// row is committed. Appends from every ingest thread are committed in groups: one thread
// gathers what is waiting, numbers it per session and writes it in one statement, so that
// the database's commit (a WAL flush) is paid once per group, not per sample.
//
// Every row carries its session's ownership epoch; the database refuses a stale one
// (cluster_db.hpp). A session whose write is refused that way, or collides with a row another
// writer holds, is dropped here and reported to onFenced(): the server must unload it, as
// another server owns it now.
//
// Every statement has a deadline (pg.hpp), so append() waits a bounded time: a database that
// hangs or cannot be reached makes appends fail with kUnavailable (at once while a reconnect
// has just failed), and the samples are not acknowledged; their vehicles send them again.
#pragma once

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "proto/journal/journal.hpp"
#include "server/cluster/pg.hpp"
#include "server/core/map_server.hpp"

namespace stereomap::cluster {

// What the database holds of a session, for recovering it: the newest snapshot and the
// records in journal order. Cloud frames the snapshot covers come without their payloads.
struct StoredSession {
  uint64_t snapshot_number = 0;  // 0: no snapshot
  std::string snapshot;          // the .ot map
  std::vector<proto::journal::JournalRecord> records;
  std::vector<uint64_t> numbers;
  uint64_t last_number = 0;
  uint64_t unreadable = 0;  // rows that did not decode (never expected; counted, skipped)
  std::string origin;       // SessionStatus::origin, from its row's summary ("" for a flight)
};

// Journal rows for one INSERT: the commit thread's groups, and a merge's batches. Bounded as
// a group is (PostgreSQL takes at most 65535 parameters): full() says when to write.
class JournalRows {
 public:
  void add(const std::string& session, uint64_t number, int64_t epoch, int kind,
           const std::vector<uint8_t>& record, const std::optional<std::vector<uint8_t>>& meta);
  // A record as its row holds it: its kind, its encoding and (clouds) the meta recovery reads.
  void add(const std::string& session, uint64_t number, int64_t epoch,
           const proto::journal::JournalRecord& record);
  bool empty() const { return rows_ == 0; }
  bool full() const;
  std::string statement() const;
  const std::vector<PgParam>& params() const { return params_; }
  void clear();

 private:
  std::vector<PgParam> params_;
  size_t rows_ = 0, bytes_ = 0;
};

class ClusterJournal : public core::IngestLog,
                       public core::SnapshotSink,
                       public core::FrameArchive {
 public:
  using FencedCallback = std::function<void(const std::string& session, const std::string& why)>;

  static common::Result<std::unique_ptr<ClusterJournal>> open(const std::string& url);
  ~ClusterJournal() override;

  // Reads what the database holds of `session` (for recovery after taking it), on a
  // connection of its own (recoveries run side by side): the newest snapshot that can be read
  // (of the two kept), and the records, the clouds that snapshot holds without their payloads.
  common::Result<StoredSession> read(const std::string& session);
  // Every journal record of `session` in order, read a page at a time (bounded in rows and
  // bytes: memory holds one page); rows that do not decode are skipped and counted. Clouds
  // numbered up to `without_payloads_up_to` may come without their payloads.
  struct RecordScan {
    uint64_t last_number = 0;  // the last row's, readable or not
    uint64_t unreadable = 0;
  };
  common::Result<RecordScan> forEachRecord(
      const std::string& session,
      const std::function<void(proto::journal::JournalRecord&& record, uint64_t number)>& visit,
      uint64_t without_payloads_up_to = 0) const;

  // This server writes `session` from now on at `epoch`, numbering after `last_number`.
  void adopt(const std::string& session, int64_t epoch, uint64_t last_number);
  // Stops writing it (lost, closed or unloaded): later appends fail with kConflict.
  void drop(const std::string& session);
  std::optional<int64_t> epochOf(const std::string& session) const;
  // Called from the commit thread, at most once per adoption, when the database fenced a
  // session; the session is already dropped. Set before the first append.
  void onFenced(FencedCallback callback);

  common::Result<uint64_t> append(const proto::CloudFrameMsg& frame) override;
  common::Result<uint64_t> append(const proto::PoseMsg& pose) override;
  common::Result<uint64_t> append(const proto::SessionEventMsg& event) override;
  common::Result<uint64_t> append(const proto::PoseCorrectionMsg& correction) override;
  common::Result<uint64_t> append(const proto::FrameAlignmentMsg& alignment) override;
  common::Status forEachFrame(const std::string& session, uint64_t after, uint64_t up_to,
                              const std::function<void(const proto::CloudFrameMsg& frame,
                                                       uint64_t number)>& visit) const override;
  common::Status saveSnapshot(const std::string& session, uint64_t journal_number,
                              const std::string& ot) override;

  // Seconds from append() to its commit, the newest kLatencyWindow, for /metrics and the
  // benchmark; and how many samples were committed, in how many groups.
  static constexpr size_t kLatencyWindow = 32768;
  std::vector<double> commitLatencies() const;
  uint64_t committedSamples() const;
  uint64_t committedGroups() const;

 private:
  struct Pending;
  ClusterJournal(std::unique_ptr<PgConnection> writer, std::unique_ptr<PgConnection> reader,
                 std::string url);
  common::Result<uint64_t> appendRecord(const std::string& session, int kind,
                                        const proto::journal::JournalRecord& record,
                                        std::optional<std::vector<uint8_t>> meta = std::nullopt);
  static PgOptions readerOptions();
  using Exec = std::function<common::Result<PgResult>(std::string_view sql,
                                                      const std::vector<PgParam>& params)>;
  static common::Result<RecordScan> scanRecords(
      const std::string& session, uint64_t without_payloads_up_to, const Exec& exec,
      const std::function<void(proto::journal::JournalRecord&& record, uint64_t number)>& visit);
  void commitLoop();
  // Writes one group; the sessions the database fenced are dropped and reported.
  void commitGroup(std::vector<Pending*>& group);
  // `state`: the failing statement's SQLSTATE ("" when none came from the database).
  common::Status insertRows(std::vector<Pending*>& rows, std::string* state);
  common::Result<PgResult> readerExec(std::string_view sql,
                                      const std::vector<PgParam>& params) const;

  std::string url_;
  std::unique_ptr<PgConnection> writer_;  // the commit thread's only
  mutable std::mutex reader_mutex_;
  std::unique_ptr<PgConnection> reader_;  // reads and snapshots

  mutable std::mutex mutex_;
  std::condition_variable wake_;  // the commit thread: something waits, or stop
  std::condition_variable done_;  // appenders: a group was committed
  struct Owned {
    int64_t epoch = 0;
    uint64_t next_number = 1;
    // A failed group's outcome may be unknown: a connection lost after the database committed
    // it, before its answer came. Its rows, from this number on, were never acknowledged, and
    // their numbers were given back; the next write of the session deletes them first, in the
    // same transaction. 0: nothing in doubt.
    uint64_t doubt_from = 0;
  };
  std::map<std::string, Owned> owned_;
  // The commit thread's: when to try connecting again, and why the last try failed.
  std::chrono::steady_clock::time_point retry_connect_at_{};
  std::string unreachable_why_;
  std::deque<Pending*> waiting_;
  FencedCallback on_fenced_;
  bool stop_ = false;
  std::vector<double> latencies_;
  size_t latency_next_ = 0;
  uint64_t committed_ = 0, groups_ = 0;
  std::thread committer_;
};

}  // namespace stereomap::cluster
