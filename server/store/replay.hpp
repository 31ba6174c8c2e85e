// Replaying what a store kept of a session into a MapServer, shared by the file store's
// recovery (store_admin.cpp) and the cluster's (server/cluster): poses and corrections first,
// then a snapshot, then frames and session events in journal order.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "proto/journal/journal.hpp"
#include "server/core/map_server.hpp"
#include "server/core/session_admin.hpp"

namespace stereomap::store {

// Replays the records' poses stamped no later than `until_ns` into `server`, then each
// vehicle's newest correction made by then (so that the frames replayed next are fused
// corrected); counts the poses taken into `poses`. Returns the newest correction's record
// number (0: none).
uint64_t replayPosesAndCorrections(core::MapServer& server,
                                   const proto::journal::JournalReplay& replay, int64_t until_ns,
                                   size_t& poses);

// Replays one record's frame or session event (poses and corrections are replayed before,
// by replayPosesAndCorrections): a frame numbered at most `covered_up_to` is in the restored
// snapshot (counted, not fused). Adds to `frames` and `snapshot_frames`.
void replayFrameOrEvent(core::MapServer& server, const proto::journal::JournalRecord& record,
                        uint64_t number, uint64_t covered_up_to, size_t& frames,
                        uint64_t& snapshot_frames);

// A store's records of one session, visited in journal order; with `payloads` false, clouds
// may come without theirs (the first pass of a replay needs only poses and corrections).
using RecordVisitor = std::function<void(proto::journal::JournalRecord&& record, uint64_t number)>;
using RecordSource = std::function<common::Status(bool payloads, const RecordVisitor& visit)>;

// The session as it was at `until_ns` (the time slider): a new read-only Session, loaded
// nowhere, fused at `resolution` from the poses, newest corrections and frames stamped no
// later (one cloud in memory at a time). Reads `records` twice.
common::Result<std::shared_ptr<core::Session>> replayUntil(const std::string& id, double resolution,
                                                           int64_t until_ns,
                                                           const RecordSource& records);

// Merging two sessions' journals (SessionAdmin::merge): every record of `first` and then of
// `second`, moved into session `into`; the second's poses, clouds and corrections moved by
// T_first_second, and its vehicles renamed (VEHICLE-SECOND) where the first has the same
// name: two flights of one vehicle are two trajectories in the merged session.
class MergedRecords {
 public:
  MergedRecords(const core::MergeRequest& request, const std::vector<std::string>& first_vehicles);
  // `record` of the first (source 0) or second (1) session, as the merged journal holds it.
  void apply(proto::journal::JournalRecord& record, int source) const;

 private:
  core::MergeRequest request_;
  std::vector<std::string> first_vehicles_;
};

// The vehicles that appear in `records`.
std::vector<std::string> vehiclesOf(const std::vector<proto::journal::JournalRecord>& records);

}  // namespace stereomap::store
