#include "server/store/replay.hpp"

#include <algorithm>
#include <map>
#include <set>
#include <string>

#include "proto/pose_fields.hpp"

namespace stereomap::store {

namespace {

// A vehicle's announcement that it flies in its own frame: replayed with the poses, before
// any frame, so that its frames are held apart as they were live.
bool ownFrame(const proto::SessionEventMsg& event) {
  return event.kind == proto::SessionEventKind::kStarted &&
         event.frame == proto::VehicleFrame::kOwn;
}

// `T` applied to a pose stored as position + x y z w quaternion.
void transformPose(const common::Rigid3& T, std::array<double, 3>& position,
                   std::array<double, 4>& orientation) {
  proto::fieldsFromRigid(T * proto::rigidFromFields(position, orientation), position, orientation);
}

}  // namespace

uint64_t replayPosesAndCorrections(core::MapServer& server,
                                   const proto::journal::JournalReplay& replay, int64_t until_ns,
                                   size_t& poses) {
  std::map<std::string, size_t> newest, aligned;  // vehicle -> record index
  for (size_t i = 0; i < replay.records.size(); ++i) {
    const auto& record = replay.records[i];
    if (const auto* pose = std::get_if<proto::PoseMsg>(&record)) {
      if (pose->stamp_ns <= until_ns) poses += server.ingest(*pose, core::Origin::kReplay);
    } else if (const auto* c = std::get_if<proto::PoseCorrectionMsg>(&record)) {
      if (c->stamp_ns <= until_ns) newest[c->vehicle_id] = i;
    } else if (const auto* a = std::get_if<proto::FrameAlignmentMsg>(&record)) {
      if (a->stamp_ns <= until_ns) aligned[a->vehicle_id] = i;
    } else if (const auto* e = std::get_if<proto::SessionEventMsg>(&record); e && ownFrame(*e)) {
      server.ingest(*e, core::Origin::kReplay);  // held apart before its frames come
    }
  }
  uint64_t newest_number = 0;
  for (const auto& [vehicle, i] : newest) {
    server.ingest(std::get<proto::PoseCorrectionMsg>(replay.records[i]), core::Origin::kReplay);
    newest_number = std::max(newest_number, replay.numbers[i]);
  }
  // A vehicle's alignment moves its frames as a correction does: no older snapshot holds them.
  for (const auto& [vehicle, i] : aligned) {
    server.ingest(std::get<proto::FrameAlignmentMsg>(replay.records[i]), core::Origin::kReplay);
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
    if (!ownFrame(*event)) {
      server.ingest(*event, core::Origin::kReplay);
    } else if (const auto session = server.find(event->session_id)) {
      // Taken before (held apart before its frames come); its place among the ends counts:
      // a vehicle that ended and started again is flying.
      session->markStarted(event->vehicle_id);
    }
  }
}

common::Result<std::shared_ptr<core::Session>> replayUntil(const std::string& id, double resolution,
                                                           int64_t until_ns,
                                                           const RecordSource& records) {
  // Poses and corrections first (frames without their payloads), then the frames streamed.
  proto::journal::JournalReplay kept;
  auto first = records(false, [&](proto::journal::JournalRecord&& record, uint64_t number) {
    if (std::holds_alternative<proto::CloudFrameMsg>(record)) return;
    kept.records.push_back(std::move(record));
    kept.numbers.push_back(number);
  });
  if (!first) return first.error();
  // A scratch server does the fusing, through the same ingest path as recovery; the session
  // outlives it.
  core::MapServer scratch({.resolution = resolution, .max_sessions = 1});
  auto created = scratch.createSession(id, resolution, /*read_only=*/true);
  if (!created) return created.error();
  size_t poses = 0;
  replayPosesAndCorrections(scratch, kept, until_ns, poses);
  kept = {};
  auto frames = records(true, [&](proto::journal::JournalRecord&& record, uint64_t number) {
    const auto* frame = std::get_if<proto::CloudFrameMsg>(&record);
    if (frame != nullptr && frame->stamp_ns <= until_ns) {
      scratch.ingest(*frame, core::Origin::kReplay, number);
    }
  });
  if (!frames) return frames.error();
  (*created)->waitUntilIdle();
  return scratch.unload(id);
}

void SourceVehicles::note(const proto::journal::JournalRecord& record) {
  std::visit([&](const auto& m) { all.insert(m.vehicle_id); }, record);
  if (const auto* event = std::get_if<proto::SessionEventMsg>(&record);
      event != nullptr && event->frame == proto::VehicleFrame::kOwn) {
    own_frame.insert(event->vehicle_id);
  }
}

MergedRecords::MergedRecords(const core::MergeRequest& request,
                             const std::vector<SourceVehicles>& vehicles)
    : request_(request), renamed_(request.sources.size()), own_frame_(request.sources.size()) {
  std::set<std::string> taken;
  for (size_t source = 0; source < vehicles.size() && source < renamed_.size(); ++source) {
    own_frame_[source] = vehicles[source].own_frame;
    std::vector<std::string> named;
    for (const auto& vehicle : vehicles[source].all) {
      std::string name = vehicle;
      if (taken.count(name) > 0) {
        name = (vehicle + "-" + request.sources[source].id).substr(0, proto::kMaxIdLength);
        renamed_[source][vehicle] = name;
      }
      named.push_back(name);
    }
    taken.insert(named.begin(), named.end());
  }
}

void MergedRecords::apply(proto::journal::JournalRecord& record, size_t source) const {
  std::visit(
      [&](auto& m) {
        m.session_id = request_.into;
        if (source >= renamed_.size()) return;
        const bool own_frame = own_frame_[source].count(m.vehicle_id) > 0;
        if (const auto it = renamed_[source].find(m.vehicle_id); it != renamed_[source].end()) {
          m.vehicle_id = it->second;
        }
        const auto& T = request_.sources[source].T_into_source;
        if (T.translation.isZero(0) && T.rotation.isApprox(common::Quat::Identity(), 0)) return;
        using Message = std::decay_t<decltype(m)>;
        // Its frames stay in its own frame; where that lies in the source's moves.
        if (own_frame && !std::is_same_v<Message, proto::FrameAlignmentMsg>) return;
        if constexpr (std::is_same_v<Message, proto::CloudFrameMsg>) {
          transformPose(T, m.sensor_position, m.sensor_orientation);
        } else if constexpr (std::is_same_v<Message, proto::PoseCorrectionMsg>) {
          for (auto& k : m.keyframes) transformPose(T, k.position, k.orientation);
        } else if constexpr (std::is_same_v<Message, proto::FrameAlignmentMsg>) {
          transformPose(T, m.position, m.orientation);  // own frame -> source's -> merged
        } else if constexpr (std::is_same_v<Message, proto::PoseMsg>) {
          transformPose(T, m.position, m.orientation);
          // The velocity is in the map frame too.
          const common::Vec3 v =
              T.rotation * common::Vec3(m.velocity[0], m.velocity[1], m.velocity[2]);
          m.velocity = {v.x(), v.y(), v.z()};
        }
      },
      record);
}

}  // namespace stereomap::store
