// A stored session as an MCAP file Foxglove (or Lichtblick) plays without plug-ins: every
// vehicle's poses as transforms from the map (/tf, foxglove.FrameTransform), its trajectory
// (/vehicles/ID/trajectory, foxglove.PosesInFrame: every 10 s the path so far, and at the end
// the path as corrected), its clouds (/vehicles/ID/cloud, foxglove.CompressedPointCloud: the
// journal's Draco payloads as they came; clouds in another encoding decoded to x, y, z on
// /vehicles/ID/cloud/points, foxglove.PointCloud), the map (/map, foxglove.SceneUpdate: one entity
// of cubes per tile, at the finest level whose cells fit max_map_cubes), a 2D occupancy grid of a
// height band for ground robots (/map2d, foxglove.Grid: occupancy_grid.hpp), map.bt as an
// attachment and the session's figures as metadata. Protobuf encoding (server/foxglove). The
// journal is read as a stream and the file written as it goes: memory holds one chunk and the
// trajectories.
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>

#include "common/result.hpp"
#include "proto/journal/journal.hpp"
#include "server/core/session.hpp"
#include "server/mcap/mcap_writer.hpp"

namespace stereomap::interop {

struct McapExportOptions {
  size_t max_map_cubes = 250000;
  size_t max_trajectory_poses = 1000;  // per PosesInFrame message (evenly thinned)
  int64_t trajectory_every_ns = 10'000'000'000;
  // The 2D grid's band (/map2d, foxglove.Grid): voxel centres from the lowest occupied
  // voxel's centre + grid_above_m to + grid_below_m, where a ground robot meets obstacles.
  double grid_above_m = 0.2, grid_below_m = 2.0;
  // Called now and then with the journal records read so far.
  std::function<void(uint64_t records)> progress;
};

struct McapExportSummary {
  uint64_t messages = 0, poses = 0, clouds = 0, corrections = 0;
  uint64_t unreadable_clouds = 0;  // payloads that did not decode (skipped)
  uint64_t bytes = 0;
  unsigned map_level = 0;
  size_t map_cubes = 0;
  int grid_width = 0, grid_height = 0;  // 0: no grid (nothing known in the band)
  int64_t start_ns = 0, end_ns = 0;     // the messages' log times
};

// Visits a session's journal records in order: the store's file, or a cluster's database.
using JournalSource = std::function<common::Status(
    const std::function<void(proto::journal::JournalRecord&& record)>& visit)>;

// `session`: the session replayed (its map and corrected trajectory); `journal`: its records.
// kIo when the sink fails; the journal's own damage is skipped, as replay skips it.
common::Result<McapExportSummary> writeSessionMcap(const core::Session& session,
                                                   const JournalSource& journal,
                                                   const mcap::McapWriter::Sink& sink,
                                                   const McapExportOptions& options = {});
// The store's journal file as a source (none: an imported map, with no flight).
JournalSource journalFile(const std::filesystem::path& journal);

}  // namespace stereomap::interop
