#include "server/interop/session_mcap.hpp"

#include <algorithm>
#include <map>
#include <sstream>

#include "proto/cloud_codec.hpp"
#include "proto/journal/journal.hpp"
#include "proto/pose_fields.hpp"
#include "server/core/occupancy_grid.hpp"
#include "server/foxglove/messages.hpp"
#include "server/tiles/tile_set.hpp"

namespace stereomap::interop {

namespace {

using foxglove::Schema;

// Every n-th pose so that at most `most` remain, the last always.
std::vector<common::Rigid3> thinned(const std::vector<common::Rigid3>& poses, size_t most) {
  if (poses.size() <= most || most < 2) return poses;
  std::vector<common::Rigid3> out;
  out.reserve(most);
  for (size_t i = 0; i + 1 < most; ++i) out.push_back(poses[i * (poses.size() - 1) / (most - 1)]);
  out.push_back(poses.back());
  return out;
}

// Height as colour: blue low, green middle, red high.
void heightColour(double t, foxglove::Cube* cube) {
  t = std::clamp(t, 0.0, 1.0);
  cube->r = static_cast<float>(t);
  cube->g = static_cast<float>(1.0 - std::abs(2.0 * t - 1.0));
  cube->b = static_cast<float>(1.0 - t);
}

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
    const auto tiles = session_.tiles().all();
    const double resolution = session_.tiles().resolution();
    unsigned level = 0;
    for (; level + 1 < tiles::kLevels; ++level) {
      size_t cells = 0;
      for (const auto& tile : tiles) cells += tile->cells(level).size();
      if (cells <= options_.max_map_cubes) break;
    }
    summary_.map_level = level;
    const common::Box3 bounds = session_.tiles().summary().bounds;
    const double z_low = bounds.min.z(), z_span = std::max(bounds.max.z() - bounds.min.z(), 1e-9);
    const uint16_t channel = mcap_.addChannel(schemas_[Schema::kSceneUpdate], "/map", "protobuf",
                                              {{"level", std::to_string(level)}});
    const int step = 1 << level;
    for (const auto& tile : tiles) {
      const auto& cells = tile->cells(level);
      if (cells.size() == 0) continue;
      foxglove::Entity entity;
      entity.id = "tile/" + tile->key().text();
      entity.metadata = {{"level", std::to_string(level)},
                         {"cell_m", std::to_string(resolution * step)}};
      const fusion::VoxelIndex base{tile->key().x << tiles::kTileBits,
                                    tile->key().y << tiles::kTileBits,
                                    tile->key().z << tiles::kTileBits};
      for (const uint32_t code : cells.codes) {
        const fusion::VoxelIndex c = tiles::cellInTile(code);
        foxglove::Cube cube;
        cube.centre = common::Vec3((base.x + c.x * step + 0.5 * step) * resolution,
                                   (base.y + c.y * step + 0.5 * step) * resolution,
                                   (base.z + c.z * step + 0.5 * step) * resolution);
        cube.size = resolution * step;
        heightColour((cube.centre.z() - z_low) / z_span, &cube);
        entity.cubes.push_back(cube);
      }
      summary_.map_cubes += entity.cubes.size();
      write(channel, stamp_ns, foxglove::sceneUpdate(stamp_ns, "map", {entity}));
    }
  }

  // The band above the lowest occupied voxel, from a copy of the map (the session's own is
  // never held up): nothing when the map is empty or nothing is known in the band.
  void grid(int64_t stamp_ns) {
    const common::Box3 bounds = session_.tiles().summary().bounds;
    if (bounds.empty()) return;
    auto bt = session_.mapBinary();
    if (!bt) return;
    std::istringstream in(*bt);
    auto map = fusion::OccupancyMap::load(in);
    if (!map) return;
    const double r = (*map)->resolution();
    const double floor = bounds.min.z() + r / 2;  // the lowest occupied voxel's centre
    auto grid =
        core::occupancyGrid(**map, floor + options_.grid_above_m, floor + options_.grid_below_m);
    if (!grid) return;
    const uint16_t channel =
        mcap_.addChannel(schemas_[Schema::kGrid], "/map2d", "protobuf",
                         {{"z_min", std::to_string(floor + options_.grid_above_m)},
                          {"z_max", std::to_string(floor + options_.grid_below_m)}});
    common::Rigid3 origin;
    origin.translation = common::Vec3(grid->origin_x, grid->origin_y, floor);
    write(channel, stamp_ns,
          foxglove::grid(stamp_ns, "map", origin, static_cast<uint32_t>(grid->width), r,
                         grid->cells));
    summary_.grid_width = grid->width;
    summary_.grid_height = grid->height;
  }

  void record(proto::journal::JournalRecord&& record) {
    if (auto* pose = std::get_if<proto::PoseMsg>(&record)) {
      const common::Rigid3 T = proto::rigidFromFields(pose->position, pose->orientation);
      write(tf_, pose->stamp_ns,
            foxglove::frameTransform(pose->stamp_ns, "map", pose->vehicle_id, T));
      Vehicle& v = vehicle(pose->vehicle_id);
      v.poses.push_back(T);
      if (v.poses.size() == 1) v.path_sent_ns = pose->stamp_ns;
      if (pose->stamp_ns - v.path_sent_ns >= options_.trajectory_every_ns) {
        write(v.trajectory, pose->stamp_ns,
              foxglove::posesInFrame(pose->stamp_ns, "map",
                                     thinned(v.poses, options_.max_trajectory_poses)));
        v.path_sent_ns = pose->stamp_ns;
      }
      ++summary_.poses;
    } else if (auto* frame = std::get_if<proto::CloudFrameMsg>(&record)) {
      Vehicle& v = vehicle(frame->vehicle_id);
      const common::Rigid3 pose =
          proto::rigidFromFields(frame->sensor_position, frame->sensor_orientation);
      if (frame->encoding == proto::CloudEncoding::kDraco) {
        // As it came: Foxglove decodes Draco itself (no decoding here, a twentieth the bytes).
        if (v.draco == 0) {
          v.draco = mcap_.addChannel(schemas_[Schema::kCompressedPointCloud],
                                     "/vehicles/" + frame->vehicle_id + "/cloud", "protobuf",
                                     {{"vehicle", frame->vehicle_id}});
        }
        write(v.draco, frame->stamp_ns,
              foxglove::compressedPointCloud(
                  frame->stamp_ns, "map", pose,
                  std::string_view(reinterpret_cast<const char*>(frame->payload.data()),
                                   frame->payload.size()),
                  "draco"));
        ++summary_.clouds;
        return;
      }
      auto cloud = proto::decodeCloud(frame->payload, proto::payloadInfo(*frame));
      if (!cloud) {
        ++summary_.unreadable_clouds;
        return;
      }
      if (v.points == 0) {
        v.points = mcap_.addChannel(schemas_[Schema::kPointCloud],
                                    "/vehicles/" + frame->vehicle_id + "/cloud/points", "protobuf",
                                    {{"vehicle", frame->vehicle_id}});
      }
      write(v.points, frame->stamp_ns, foxglove::pointCloud(frame->stamp_ns, "map", pose, *cloud));
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
      corrected[pose.vehicle_id].push_back(pose.T_map_body);
    }
    for (const auto& [id, poses] : corrected) {
      write(vehicle(id).trajectory, end,
            foxglove::posesInFrame(end, "map", thinned(poses, options_.max_trajectory_poses)));
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

  Vehicle& vehicle(const std::string& id) {
    auto [it, added] = vehicles_.try_emplace(id);
    if (added) {
      const std::map<std::string, std::string> metadata{{"vehicle", id}};
      it->second.trajectory = mcap_.addChannel(
          schemas_[Schema::kPosesInFrame], "/vehicles/" + id + "/trajectory", "protobuf", metadata);
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
  McapExportSummary summary_;
};

}  // namespace

common::Result<McapExportSummary> writeSessionMcap(const core::Session& session,
                                                   const std::filesystem::path& journal,
                                                   const mcap::McapWriter::Sink& sink,
                                                   const McapExportOptions& options) {
  Export out(session, sink, options);
  // The map first, at the first pose's time: the finished map is there from the start.
  const auto first = session.trajectory(0, 1);
  out.map(first.empty() ? 0 : first.front().stamp_ns);
  out.grid(first.empty() ? 0 : first.front().stamp_ns);
  uint64_t records = 0;
  std::error_code absent;
  if (!std::filesystem::exists(journal, absent)) {  // an imported map: no journal, no flight
    return out.finish();
  }
  auto read = proto::journal::visitJournal(journal, 0,
                                           [&](proto::journal::JournalRecord&& record, uint64_t) {
                                             out.record(std::move(record));
                                             if (++records % 256 == 0 && options.progress)
                                               options.progress(records);
                                           });
  if (!read) return read.error();
  if (options.progress) options.progress(records);
  return out.finish();
}

}  // namespace stereomap::interop
