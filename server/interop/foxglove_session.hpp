// A session as Foxglove's channels show it, shared by the MCAP export (session_mcap.hpp) and
// the live Foxglove WebSocket server (server/viewers/foxglove_hub.hpp), so that a layout made
// for one works with the other: the topics, each vehicle's clouds as messages, the map's tiles
// as SceneUpdate entities of cubes, and the 2D grid of the band where a ground robot meets
// obstacles.
//
//   auto cloud = cloudMessage(frame);  // CompressedPointCloud (Draco as it came) or PointCloud
//   write(cloudTopic(frame.vehicle_id, cloud->schema), cloud->bytes);
#pragma once

#include <map>
#include <optional>
#include <string>
#include <vector>

#include "common/result.hpp"
#include "proto/messages.hpp"
#include "server/core/session.hpp"
#include "server/foxglove/messages.hpp"
#include "server/tiles/tile_set.hpp"

namespace stereomap::interop {

inline constexpr const char* kMapFrame = "map";  // each vehicle's frame is its id

std::string trajectoryTopic(const std::string& vehicle);  // /vehicles/ID/trajectory
// A trajectory's path for PosesInFrame: every n-th pose so that at most `most` remain, the
// last always.
std::vector<common::Rigid3> thinned(const std::vector<common::Rigid3>& poses, size_t most);
// /vehicles/ID/cloud (CompressedPointCloud) or /vehicles/ID/cloud/points (PointCloud).
std::string cloudTopic(const std::string& vehicle, foxglove::Schema schema);

struct CloudMessage {
  foxglove::Schema schema;
  std::string bytes;
};
// A Draco payload as it came (Foxglove decodes it: no decoding here, a twentieth the bytes);
// other encodings decoded to x, y, z. nullopt: the payload does not decode. `T_map_sent`
// places the sensor pose the vehicle sent (framePlacement()).
std::optional<CloudMessage> cloudMessage(
    const proto::CloudFrameMsg& frame,
    const common::Rigid3& T_map_sent = common::Rigid3::identity());

// Where what a vehicle sends goes in the session's map frame: the identity for a vehicle in
// the session's frame, its alignment for one joined in its own frame, nullopt while it is
// held apart (nowhere yet: its poses and clouds are left out).
std::optional<common::Rigid3> framePlacement(const core::Session& session,
                                             const std::string& vehicle);

// The finest level whose occupied cells, over every tile, are at most `max_cubes`.
unsigned mapLevel(const std::vector<tiles::TileInfo>& tiles, size_t max_cubes);
// One tile's cells at `level` as cubes coloured by height over [z_low, z_low + z_span]; its id
// is "tile/X_Y_Z" (the same tile keeps its entity as the map grows).
foxglove::Entity tileEntity(const tiles::Tile& tile, unsigned level, double resolution,
                            double z_low, double z_span);
std::string tileEntityId(const tiles::TileKey& key);
// The same cubes as entities of one 16-voxel block each ("tile/X_Y_Z/B", B in 0..63), by B:
// what changes of a tile as fusion goes on is then sent alone (the live map).
std::map<uint16_t, foxglove::Entity> tileBlocks(const tiles::Tile& tile, unsigned level,
                                                double resolution, double z_low, double z_span);

// The band a ground robot meets obstacles in: voxel centres from the lowest occupied voxel's
// centre + above_m to + below_m, as a foxglove.Grid (read from a copy of the map: the session's
// own is never held up). kNotFound when the map is empty or nothing is known in the band.
struct GroundGrid {
  std::string message;  // foxglove.Grid
  double z_min = 0, z_max = 0;
  int width = 0, height = 0;
};
common::Result<GroundGrid> groundGrid(const core::Session& session, int64_t stamp_ns,
                                      double above_m, double below_m);

}  // namespace stereomap::interop
