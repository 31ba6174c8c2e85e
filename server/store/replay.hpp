// Replaying what a store kept of a session into a MapServer, shared by the file store's
// recovery (store_admin.cpp) and the cluster's (server/cluster): poses and corrections first,
// then a snapshot, then frames and session events in journal order.
#pragma once

#include <cstdint>

#include "proto/journal/journal.hpp"
#include "server/core/map_server.hpp"

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

}  // namespace stereomap::store
