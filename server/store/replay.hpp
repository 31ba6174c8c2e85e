// Replaying what a store kept of a session into a MapServer, shared by the file store's
// recovery (store_admin.cpp) and the cluster's (server/cluster): poses and corrections first,
// then a snapshot, then frames and session events in journal order.
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <set>
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

// What a merge learns of a source in a first reading: its vehicles, and which of them fly in
// their own frame (their frames stay in it: only their alignment moves).
struct SourceVehicles {
  std::set<std::string> all, own_frame;
  void note(const proto::journal::JournalRecord& record);
};

// Merging sessions' journals (SessionAdmin::merge): every record of each source in turn,
// moved into session `into`; each source's poses, clouds, corrections and alignments moved by
// its transform (a vehicle in its own frame: its alignment only), and its vehicles renamed
// (VEHICLE-SOURCE) where an earlier source has one of the same name: two flights of one
// vehicle are two trajectories in the merged session.
class MergedRecords {
 public:
  // `vehicles[i]`: source i's (SourceVehicles::note over its records).
  MergedRecords(const core::MergeRequest& request, const std::vector<SourceVehicles>& vehicles);
  // `record` of source `source` (an index into request.sources), as the merged journal holds it.
  void apply(proto::journal::JournalRecord& record, size_t source) const;

 private:
  core::MergeRequest request_;
  std::vector<std::map<std::string, std::string>> renamed_;  // per source: vehicle -> new name
  std::vector<std::set<std::string>> own_frame_;             // per source
};

}  // namespace stereomap::store
