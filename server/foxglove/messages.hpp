// Foxglove's message schemas (docs.foxglove.dev, "Message schemas") encoded as protobuf, and
// the descriptor sets that define them (protoc's, of proto/foxglove): what a session's MCAP
// export and the Foxglove WebSocket server send, so that Foxglove and Lichtblick show them
// without plug-ins. Protobuf, not JSON: a cloud's points travel as raw bytes, not base64, and
// every reader of MCAP decodes it from the descriptors in the file (docs/BENCHMARKS.md).
//
//   mcap.addSchema(std::string(schemaName(Schema::kPointCloud)), "protobuf",
//                  descriptorSet(Schema::kPointCloud));
//   mcap.write(channel, stamp, pointCloud(stamp, "map", T_map_sensor, cloud));
#pragma once

#include <cstdint>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "common/geometry.hpp"
#include "common/point_cloud.hpp"

namespace stereomap::foxglove {

enum class Schema {
  kFrameTransform,
  kPosesInFrame,
  kPointCloud,
  kCompressedPointCloud,
  kSceneUpdate,
  kGrid
};

std::string_view schemaName(Schema schema);     // "foxglove.PointCloud"
std::string_view descriptorSet(Schema schema);  // a serialised FileDescriptorSet, imports included
// RFC 4648 base64 (with padding): how a Foxglove WebSocket channel carries its descriptor set.
std::string base64(std::string_view bytes);

// foxglove.FrameTransform: child's pose in parent's frame.
std::string frameTransform(int64_t stamp_ns, std::string_view parent, std::string_view child,
                           const common::Rigid3& T_parent_child);
// foxglove.PosesInFrame.
std::string posesInFrame(int64_t stamp_ns, std::string_view frame,
                         const std::vector<common::Rigid3>& poses);
// foxglove.PointCloud of x, y, z (float32, 12 bytes a point; and intensity, uint8, when the
// cloud has it: 13), the points in `pose`'s frame placed in `frame`.
std::string pointCloud(int64_t stamp_ns, std::string_view frame, const common::Rigid3& pose,
                       const common::PointCloud& cloud);

// foxglove.Grid of one int8 field "occupancy" (nav_msgs' values: -1 unknown, 0 free, 100
// occupied), `columns` cells a row, rows along +y from `origin` (the first cell's corner).
std::string grid(int64_t stamp_ns, std::string_view frame, const common::Rigid3& origin,
                 uint32_t columns, double cell_m, const std::vector<int8_t>& cells);

// foxglove.CompressedPointCloud: a payload as it came (`format` "draco": the vehicle's own
// Draco bytes, decoded by the reader), placed by `pose` in `frame`.
std::string compressedPointCloud(int64_t stamp_ns, std::string_view frame,
                                 const common::Rigid3& pose, std::string_view data,
                                 std::string_view format);

// foxglove.SceneUpdate of entities made of axis-aligned cubes; `deleted`: ids of entities
// removed (a live map's tile that emptied).
struct Cube {
  common::Vec3 centre;
  double size = 0;
  float r = 1, g = 1, b = 1, a = 1;
};
struct Entity {
  std::string id;
  std::vector<Cube> cubes;
  std::vector<std::pair<std::string, std::string>> metadata;
};
std::string sceneUpdate(int64_t stamp_ns, std::string_view frame,
                        const std::vector<Entity>& entities,
                        const std::vector<std::string>& deleted = {});
// One entity, and one deletion, as the SceneUpdate fields they are: a SceneUpdate's bytes are
// any concatenation of them (protobuf's repeated fields), so an update can be put together from
// entities encoded once (the live map: server/viewers/foxglove_hub).
std::string sceneEntityField(int64_t stamp_ns, std::string_view frame, const Entity& entity);
std::string sceneDeletionField(int64_t stamp_ns, std::string_view id);

}  // namespace stereomap::foxglove
