// The server's core: validates every incoming sample, counts and logs the bad ones
// (rate-limited), and routes the good ones to their session (created on first sight).
// Thread-safe: ingest() may be called from several DDS reader threads at once.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <tuple>
#include <vector>

#include "common/result.hpp"
#include "common/worker_pool.hpp"
#include "proto/dds.hpp"
#include "proto/messages.hpp"
#include "server/core/metrics.hpp"
#include "server/core/session.hpp"
#include "server/core/validate.hpp"

namespace stereomap::core {

// Where accepted samples are made durable before they count as received (the store's
// journal). Each append returns the sample's journal record number (> 0, growing). Called
// from the ingest threads; implementations are thread-safe.
class IngestLog {
 public:
  virtual ~IngestLog() = default;
  virtual common::Result<uint64_t> append(const proto::CloudFrameMsg& frame) = 0;
  virtual common::Result<uint64_t> append(const proto::PoseMsg& pose) = 0;
  virtual common::Result<uint64_t> append(const proto::SessionEventMsg& event) = 0;
  virtual common::Result<uint64_t> append(const proto::PoseCorrectionMsg& correction) = 0;
  virtual common::Result<uint64_t> append(const proto::FrameAlignmentMsg& alignment) = 0;
};

// Where journaled frames can be read again (the store): a session's map is fused again from
// them when a vehicle's pose graph corrects the poses it sent. Called from re-fusion threads.
class FrameArchive {
 public:
  virtual ~FrameArchive() = default;
  // Every intact cloud frame of `session` numbered in (after, up_to], in journal order.
  virtual common::Status forEachFrame(const std::string& session, uint64_t after, uint64_t up_to,
                                      const std::function<void(const proto::CloudFrameMsg& frame,
                                                               uint64_t number)>& visit) const = 0;
};

// Where sessions' map snapshots go (the store): a .ot of the map holding every frame up to
// journal record `journal_number`. Called from fusion worker threads.
class SnapshotSink {
 public:
  virtual ~SnapshotSink() = default;
  virtual common::Status saveSnapshot(const std::string& session, uint64_t journal_number,
                                      const std::string& ot) = 0;
};

// Whether the store can be written. Degraded (a full or failing disk): the server serves what
// it has and refuses new samples, which it cannot keep, until a write succeeds again.
struct StoreHealth {
  bool ok = true;
  std::string reason;           // when degraded: what failed, naming the file and the cause
  int64_t since_ns = 0;         // when it became degraded
  int64_t last_failure_ns = 0;  // the latest failed write
};

// A live sample is journaled; a replayed one (crash recovery) already was, and waits for
// room in the fusion queue instead of being dropped; a covered one is already in the
// restored snapshot (counted and de-duplicated, not fused again).
enum class Origin { kLive, kReplay, kCovered };

struct MapServerOptions {
  double resolution = 0.1;
  size_t queue_capacity = 200;
  size_t max_sessions = 256;
  IngestLimits limits;
  IngestLog* log = nullptr;           // not owned; nullptr: nothing is journaled
  SnapshotSink* snapshots = nullptr;  // not owned; nullptr: no snapshots
  FrameArchive* archive = nullptr;    // not owned; nullptr: corrections never re-fuse a map
  size_t snapshot_every = 100;        // frames between snapshots
  std::chrono::milliseconds snapshot_interval{0};  // and at least this long (Session::Options)
};

// A frame as fusion takes it (the cloud decoded, the pose as sent), or the reason it is not
// a valid frame.
std::optional<Rejection> fusionJobFrom(const proto::CloudFrameMsg& frame,
                                       const IngestLimits& limits, uint64_t journal_number,
                                       FusionJob& job);

class MapServer {
 public:
  explicit MapServer(const MapServerOptions& options);

  // Each returns true when the sample was accepted. A sample seen before (its stream and seq
  // taken already: a vehicle's spool or DDS's history sending it again, receipts.hpp) is
  // counted as a duplicate and skipped.
  // `journal_number`: a replayed or covered frame's record number in the journal.
  // `arrived`: when the frame reached this server (the start of its publication lag); unset:
  // now.
  bool ingest(const proto::CloudFrameMsg& frame, Origin origin = Origin::kLive,
              uint64_t journal_number = 0, std::chrono::steady_clock::time_point arrived = {});
  bool ingest(const proto::PoseMsg& pose, Origin origin = Origin::kLive);
  bool ingest(const proto::SessionEventMsg& event, Origin origin = Origin::kLive);
  // A vehicle's pose graph's correction (newest per vehicle wins): live ones are journaled
  // and re-fuse the session's map; replayed ones (recovery, which sets them before it fuses
  // the frames) do not. Refused (counted, reason "unknown_poses") when none of its keyframes
  // is a pose the vehicle sent.
  bool ingest(const proto::PoseCorrectionMsg& correction, Origin origin = Origin::kLive);
  // A vehicle in its own frame aligned into its session's (FrameAligner; or at identity, the
  // session's reference vehicle): a live one is journaled, then the vehicle is joined
  // (Session::join: what it held is fused again in the session's frame); a replayed one
  // (recovery, before the frames) joins it without re-fusion. False when the session is not
  // loaded, the record is not valid or the journal could not keep it.
  bool ingest(const proto::FrameAlignmentMsg& alignment, Origin origin = Origin::kLive);
  // A vehicle's view of the landing pad: kept as the newest per vehicle in its session, never
  // journaled. Refused (reason "unknown_session") when the session does not exist: a
  // landing target alone does not make one.
  bool ingest(const proto::LandingTargetMsg& target);
  // A vehicle's own counters: kept as the newest per vehicle in its session, never journaled,
  // shown in its status. Refused (reason "unknown_session") when the session is not loaded.
  bool ingest(const proto::VehicleStatusMsg& status);
  // A sample DDS delivered that its type's checks refused (proto::Reader::take: an
  // enumeration out of range): counted as received and rejected (reason "bad_enum") under its
  // type, and logged like every rejection.
  void refuse(const proto::RefusedSample& sample);

  // Creates session `id` (recovery, or opening a stored session read-only) at its own
  // resolution; fails when it is already loaded or the session limit is reached.
  // `snapshots` false: none is taken (its journal's record numbers cannot be trusted yet).
  common::Result<std::shared_ptr<Session>> createSession(const std::string& id, double resolution,
                                                         bool read_only, bool snapshots = true);
  // Unloads a session that was closed into the store and returns it: later samples for it
  // are refused (reason session_closed) until it is opened again or forgotten.
  std::shared_ptr<Session> unload(const std::string& id);
  // Marks ids as closed (kept in the store, not loaded) or forgets them (deleted).
  void markClosed(const std::string& id);
  void forget(const std::string& id);

  // The store's state: set degraded by a failed journal write (or by the store at start-up),
  // ok again by the next write that succeeds. Shown by /healthz, /metrics and the log.
  void reportStoreProblem(const std::string& reason);
  void reportStoreOk();
  StoreHealth storeHealth() const;

  // Marks ended every live session whose vehicles sent nothing for `timeout` (a vehicle that
  // stopped while the server was down never says so). Called periodically.
  void endSilentSessions(std::chrono::milliseconds timeout);

  // What the live sessions have journaled of their vehicles' streams, where it changed (or a
  // vehicle sent a sample again) since the last call: for the Ack topic, a few times a second.
  // And the answers to vehicles still sending to a closed or read-only session
  // (AckStatus::kSessionClosed, answerClosed).
  std::vector<proto::AckMsg> takeAcks();
  // Tells a vehicle's stream that its session takes no more samples (`reason`, for its log):
  // an AckStatus::kSessionClosed acknowledgement in the next takeAcks, then again at most every
  // kClosedAnswerEvery while the stream still sends (each call is such a sample). Called for
  // every live sample refused as session_closed or read_only, and by a cluster server for a
  // closed session's announcements. At most kMaxClosedAnswers streams are answered at once.
  void answerClosed(const std::string& session_id, const std::string& vehicle_id, uint64_t stream,
                    const std::string& reason);
  static constexpr std::chrono::seconds kClosedAnswerEvery{1};
  static constexpr size_t kMaxClosedAnswers = 4096;

  std::vector<std::shared_ptr<Session>> sessions() const;  // in creation order
  std::shared_ptr<Session> find(const std::string& id) const;
  // Prometheus text, with per-session gauges refreshed.
  std::string metricsText() const;
  const Metrics& metrics() const { return metrics_; }
  Metrics& metrics() { return metrics_; }  // for series the server's modes add (cluster)
  const MapServerOptions& options() const { return options_; }

 private:
  // The session, created on first sight; nullptr with `refusal` set when it cannot be.
  std::shared_ptr<Session> sessionFor(const std::string& id, const char* topic,
                                      std::optional<Rejection>& refusal);
  Session::Options sessionOptions(const std::string& id, double resolution, bool read_only,
                                  bool snapshots = true) const;
  // Counts the sample (a live one's bytes by vehicle and in its session, which it keeps live)
  // and returns its session, or nullptr (counted, logged) when rejected.
  template <typename Message>
  std::shared_ptr<Session> admit(const char* topic, const Message& message,
                                 std::optional<Rejection> rejection, Origin origin);
  // admit() for a sample that belongs to a loaded session and makes none (landing targets,
  // vehicles' status): refused as unknown_session when its session is not loaded.
  template <typename Message>
  std::shared_ptr<Session> admitToLoaded(const char* topic, const Message& message,
                                         std::optional<Rejection> rejection);
  // A live sample's bytes and, for a pose, its age on arrival.
  // Under mutex_: the vehicles of a session with links_ entries; forgetting them and their
  // metrics when the session goes.
  size_t vehicleLinks(const std::string& session_id) const;
  void forgetLinks(const std::string& session_id);
  void noteTraffic(const char* topic, const std::string& session_id, const std::string& vehicle_id,
                   size_t bytes, std::optional<int64_t> pose_stamp_ns);
  void reject(const char* topic, const Rejection& rejection, const std::string& from);
  // Skips duplicates and journals live samples: the journal record number (0 when nothing
  // was journaled), or nullopt when the sample must go no further.
  template <typename Message>
  std::optional<uint64_t> record(const char* topic, const Message& message, Session& session,
                                 Origin origin);

  const MapServerOptions options_;
  // Fusion's helper threads, shared by every session's worker (they live with the process).
  std::shared_ptr<common::WorkerPool> pool_;
  mutable Metrics metrics_;
  mutable std::mutex mutex_;
  std::map<std::string, std::shared_ptr<Session>> sessions_;
  std::vector<std::string> order_;
  std::set<std::string> closed_;
  std::map<std::string, uint64_t> rejections_by_reason_;  // for rate-limited logging
  // Streams to tell their session is closed: (session, vehicle, stream) -> the reason, when
  // last told (steady ns; 0: never), and whether a sample came since. Under mutex_.
  struct ClosedAnswer {
    std::string reason;
    int64_t told_ns = 0;
    bool asked = true;
  };
  std::map<std::tuple<std::string, std::string, uint64_t>, ClosedAnswer> closed_answers_;
  // What each vehicle's link delivers (session, vehicle): its poses' ages on arrival, the
  // last ones. Any vehicle id is valid, so the number of vehicles with series of their own is
  // bounded (per session and in all); later ones share one bytes series and have no latency.
  // A session's entries and series go when it is unloaded.
  struct VehicleLink {
    std::vector<double> pose_latency_s;  // a ring of the newest
    size_t next = 0;
    int64_t newest_pose_ns = INT64_MIN;
  };
  std::map<std::pair<std::string, std::string>, VehicleLink> links_;  // under mutex_
  std::atomic<bool> store_ok_{true};  // fast path of reportStoreOk()
  StoreHealth store_health_;          // under mutex_
};

}  // namespace stereomap::core
