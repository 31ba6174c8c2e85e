#include "server/cluster/cluster_recovery.hpp"

#include <spdlog/spdlog.h>

#include <limits>
#include <sstream>

#include "server/store/replay.hpp"

namespace stereomap::cluster {

common::Status recoverSession(core::MapServer& server, ClusterJournal& journal,
                              const Ownership& owned, StoredSession& stored, size_t& frames,
                              size_t& poses, bool wait_until_fused) {
  auto created = server.createSession(owned.session, owned.resolution, owned.read_only,
                                      /*snapshots=*/!owned.read_only);
  if (!created) return created.error();
  const auto& session = *created;
  session->setOrigin(stored.origin);
  proto::journal::JournalReplay kept;
  kept.records = std::move(stored.records);
  kept.numbers = std::move(stored.numbers);
  const uint64_t newest_correction =
      store::replayPosesAndCorrections(server, kept, std::numeric_limits<int64_t>::max(), poses);
  uint64_t covered_up_to = 0;
  if (!stored.snapshot.empty() && stored.snapshot_number >= newest_correction) {
    std::istringstream ot(stored.snapshot);
    if (auto restored = session->restore(ot, stored.snapshot_number); restored) {
      covered_up_to = stored.snapshot_number;
    } else {
      spdlog::warn("session '{}': its snapshot {} is unusable ({}); fusing every frame again",
                   owned.session, stored.snapshot_number, restored.error().message);
    }
  }
  uint64_t snapshot_frames = 0;
  if (covered_up_to == stored.snapshot_number) {
    for (size_t i = 0; i < kept.records.size(); ++i) {
      store::replayFrameOrEvent(server, kept.records[i], kept.numbers[i], covered_up_to, frames,
                                snapshot_frames);
    }
  } else {
    // The frames the snapshot was to hold came without their payloads: read them again.
    for (size_t i = 0; i < kept.records.size(); ++i) {
      if (!std::holds_alternative<proto::CloudFrameMsg>(kept.records[i])) {
        store::replayFrameOrEvent(server, kept.records[i], kept.numbers[i], 0, frames,
                                  snapshot_frames);
      }
    }
    auto again = journal.forEachFrame(owned.session, 0, std::numeric_limits<int64_t>::max(),
                                      [&](const proto::CloudFrameMsg& frame, uint64_t number) {
                                        store::replayFrameOrEvent(server, frame, number, 0, frames,
                                                                  snapshot_frames);
                                      });
    if (!again) return again.error();
  }
  if (wait_until_fused) session->waitUntilIdle();
  return common::Ok{};
}

}  // namespace stereomap::cluster
