#include "server/interop/session_mcap.hpp"

#include <algorithm>
#include <map>

#include "proto/journal/journal.hpp"
#include "proto/pose_fields.hpp"
#include "server/foxglove/messages.hpp"
#include "server/interop/foxglove_session.hpp"

namespace stereomap::interop {

namespace {

using foxglove::Schema;

class Export {
 public:
  Export(const core::Session& session, const mcap::McapWriter::Sink& sink,
         const McapExportOptions& options)
      : session_(session), options_(options), mcap_(sink) {
    for (Schema schema : {Schema::kFrameTransform, Schema::kPosesInFrame, Schema::kPointCloud,
                          Schema::kCompressedPointCloud, Schema::kSceneUpdate, Schema::kGrid}) {
      schemas_[schema] = mcap_.addSchema(std::string(foxglove::schemaName(schema)), "protobuf",
                                         foxglove::descriptorSet(schema));
    }
    tf_ = mcap_.addChannel(schemas_[Schema::kFrameTransform], "/tf", "protobuf");
  }

  void map(int64_t stamp_ns) {
    const auto& tiles = session_.tiles();
    const unsigned level = mapLevel(tiles.list(), options_.max_map_cubes);
    summary_.map_level = level;
    const common::Box3 bounds = tiles.summary().bounds;
    const uint16_t channel = mcap_.addChannel(schemas_[Schema::kSceneUpdate], "/map", "protobuf",
                                              {{"level", std::to_string(level)}});
    for (const auto& tile : tiles.all()) {
      if (tile->cells(level).size() == 0) continue;
      auto entity = tileEntity(*tile, level, tiles.resolution(), bounds.min.z(),
                               bounds.max.z() - bounds.min.z());
      summary_.map_cubes += entity.cubes.size();
      write(channel, stamp_ns, foxglove::sceneUpdate(stamp_ns, kMapFrame, {entity}));
    }
  }

  // The ground band's grid; nothing when the map is empty or nothing is known in the band.
  void grid(int64_t stamp_ns) {
    auto grid = groundGrid(session_, stamp_ns, options_.grid_above_m, options_.grid_below_m);
    if (!grid) return;
    const uint16_t channel = mcap_.addChannel(
        schemas_[Schema::kGrid], "/map2d", "protobuf",
        {{"z_min", std::to_string(grid->z_min)}, {"z_max", std::to_string(grid->z_max)}});
    write(channel, stamp_ns, grid->message);
    summary_.grid_width = grid->width;
    summary_.grid_height = grid->height;
  }

  void record(proto::journal::JournalRecord&& record) {
    if (auto* pose = std::get_if<proto::PoseMsg>(&record)) {
      const auto placed = placement(pose->vehicle_id);
      if (!placed) return;  // held apart: nowhere in the map's frame
      const common::Rigid3 T = *placed * proto::rigidFromFields(pose->position, pose->orientation);
      write(tf_, pose->stamp_ns,
            foxglove::frameTransform(pose->stamp_ns, kMapFrame, pose->vehicle_id, T));
      Vehicle& v = vehicle(pose->vehicle_id);
      v.poses.push_back(T);
      if (v.poses.size() == 1) v.path_sent_ns = pose->stamp_ns;
      if (pose->stamp_ns - v.path_sent_ns >= options_.trajectory_every_ns) {
        write(v.trajectory, pose->stamp_ns,
              foxglove::posesInFrame(pose->stamp_ns, kMapFrame,
                                     thinned(v.poses, options_.max_trajectory_poses)));
        v.path_sent_ns = pose->stamp_ns;
      }
      ++summary_.poses;
    } else if (auto* frame = std::get_if<proto::CloudFrameMsg>(&record)) {
      const auto placed = placement(frame->vehicle_id);
      if (!placed) return;
      Vehicle& v = vehicle(frame->vehicle_id);
      auto cloud = cloudMessage(*frame, *placed);
      if (!cloud) {
        ++summary_.unreadable_clouds;
        return;
      }
      uint16_t& channel = cloud->schema == Schema::kPointCloud ? v.points : v.draco;
      if (channel == 0) {
        channel =
            mcap_.addChannel(schemas_[cloud->schema], cloudTopic(frame->vehicle_id, cloud->schema),
                             "protobuf", {{"vehicle", frame->vehicle_id}});
      }
      write(channel, frame->stamp_ns, cloud->bytes);
      ++summary_.clouds;
    } else if (std::holds_alternative<proto::PoseCorrectionMsg>(record)) {
      ++summary_.corrections;
    }
  }

  // The corrected trajectories, the map file and the figures; then the summary.
  common::Result<McapExportSummary> finish() {
    const int64_t end = summary_.messages > 0 ? summary_.end_ns : 0;
    std::map<std::string, std::vector<common::Rigid3>> corrected;
    for (const auto& pose : session_.trajectory()) {
      if (!pose.held) corrected[pose.vehicle_id].push_back(pose.T_map_body);
    }
    for (const auto& [id, poses] : corrected) {
      write(vehicle(id).trajectory, end,
            foxglove::posesInFrame(end, kMapFrame, thinned(poses, options_.max_trajectory_poses)));
    }
    if (auto map = session_.mapBinary(); map && !map->empty()) {
      mcap_.attach("map.bt", "application/octet-stream", static_cast<uint64_t>(end), *map);
    }
    const core::SessionStatus status = session_.status();
    std::string vehicles;
    for (const auto& id : status.vehicles) vehicles += (vehicles.empty() ? "" : ",") + id;
    mcap_.metadata("stereomap.session",
                   {{"id", status.id},
                    {"state", core::stateName(status)},
                    {"resolution_m", std::to_string(status.resolution)},
                    {"vehicles", vehicles},
                    {"frames", std::to_string(status.frames_received)},
                    {"poses", std::to_string(status.poses)},
                    {"occupied_voxels", std::to_string(status.occupied_voxels)},
                    {"corrections", std::to_string(status.corrections)},
                    {"map_level", std::to_string(summary_.map_level)}});
    if (auto closed = mcap_.close(); !closed) return closed.error();
    summary_.bytes = mcap_.bytesWritten();
    return summary_;
  }

 private:
  struct Vehicle {
    uint16_t trajectory = 0;
    uint16_t draco = 0, points = 0;  // cloud channels, made when a first cloud comes
    std::vector<common::Rigid3> poses;
    int64_t path_sent_ns = 0;
  };

  // framePlacement(), asked once a vehicle: the export shows the session as it is now.
  const std::optional<common::Rigid3>& placement(const std::string& id) {
    auto found = placements_.find(id);
    if (found == placements_.end())
      found = placements_.emplace(id, framePlacement(session_, id)).first;
    return found->second;
  }

  Vehicle& vehicle(const std::string& id) {
    auto [it, added] = vehicles_.try_emplace(id);
    if (added) {
      const std::map<std::string, std::string> metadata{{"vehicle", id}};
      it->second.trajectory = mcap_.addChannel(schemas_[Schema::kPosesInFrame], trajectoryTopic(id),
                                               "protobuf", metadata);
    }
    return it->second;
  }

  void write(uint16_t channel, int64_t stamp_ns, const std::string& bytes) {
    const auto t = static_cast<uint64_t>(std::max<int64_t>(stamp_ns, 0));
    mcap_.write(channel, t, bytes);
    if (summary_.messages == 0) summary_.start_ns = summary_.end_ns = static_cast<int64_t>(t);
    summary_.start_ns = std::min<int64_t>(summary_.start_ns, static_cast<int64_t>(t));
    summary_.end_ns = std::max<int64_t>(summary_.end_ns, static_cast<int64_t>(t));
    ++summary_.messages;
  }

  const core::Session& session_;
  const McapExportOptions& options_;
  mcap::McapWriter mcap_;
  std::map<Schema, uint16_t> schemas_;
  uint16_t tf_ = 0;
  std::map<std::string, Vehicle> vehicles_;
  std::map<std::string, std::optional<common::Rigid3>> placements_;
  McapExportSummary summary_;
};

}  // namespace

common::Result<McapExportSummary> writeSessionMcap(const core::Session& session,
                                                   const JournalSource& journal,
                                                   const mcap::McapWriter::Sink& sink,
                                                   const McapExportOptions& options) {
  Export out(session, sink, options);
  // The map first, at the first pose's time: the finished map is there from the start.
  const auto first = session.trajectory(0, 1);
  out.map(first.empty() ? 0 : first.front().stamp_ns);
  out.grid(first.empty() ? 0 : first.front().stamp_ns);
  uint64_t records = 0;
  auto read = journal([&](proto::journal::JournalRecord&& record) {
    out.record(std::move(record));
    if (++records % 256 == 0 && options.progress) options.progress(records);
  });
  if (!read) return read.error();
  if (options.progress) options.progress(records);
  return out.finish();
}

JournalSource journalFile(const std::filesystem::path& journal) {
  return [journal](const std::function<void(proto::journal::JournalRecord &&)>& visit) {
    std::error_code absent;
    if (!std::filesystem::exists(journal, absent)) return common::Status(common::Ok{});
    auto read = proto::journal::visitJournal(
        journal, 0,
        [&](proto::journal::JournalRecord&& record, uint64_t) { visit(std::move(record)); });
    if (!read) return common::Status(read.error());
    return common::Status(common::Ok{});
  };
}

}  // namespace stereomap::interop
