#include "server/store/replay.hpp"

#include <map>
#include <string>

namespace stereomap::store {

uint64_t replayPosesAndCorrections(core::MapServer& server,
                                   const proto::journal::JournalReplay& replay, int64_t until_ns,
                                   size_t& poses) {
  std::map<std::string, size_t> newest;  // vehicle -> record index
  for (size_t i = 0; i < replay.records.size(); ++i) {
    const auto& record = replay.records[i];
    if (const auto* pose = std::get_if<proto::PoseMsg>(&record)) {
      if (pose->stamp_ns <= until_ns) poses += server.ingest(*pose, core::Origin::kReplay);
    } else if (const auto* c = std::get_if<proto::PoseCorrectionMsg>(&record)) {
      if (c->stamp_ns <= until_ns) newest[c->vehicle_id] = i;
    }
  }
  uint64_t newest_number = 0;
  for (const auto& [vehicle, i] : newest) {
    server.ingest(std::get<proto::PoseCorrectionMsg>(replay.records[i]), core::Origin::kReplay);
    newest_number = std::max(newest_number, replay.numbers[i]);
  }
  return newest_number;
}

void replayFrameOrEvent(core::MapServer& server, const proto::journal::JournalRecord& record,
                        uint64_t number, uint64_t covered_up_to, size_t& frames,
                        uint64_t& snapshot_frames) {
  if (const auto* frame = std::get_if<proto::CloudFrameMsg>(&record)) {
    const bool covered = number <= covered_up_to;
    frames +=
        server.ingest(*frame, covered ? core::Origin::kCovered : core::Origin::kReplay, number);
    snapshot_frames += covered;
  } else if (const auto* event = std::get_if<proto::SessionEventMsg>(&record)) {
    server.ingest(*event, core::Origin::kReplay);
  }
}

}  // namespace stereomap::store
