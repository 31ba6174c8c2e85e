#include "server/foxglove/messages.hpp"

#include <algorithm>
#include <cstring>

namespace stereomap::foxglove {

namespace detail {
extern const std::string_view kFrameTransformDescriptors, kPosesInFrameDescriptors,
    kPointCloudDescriptors, kCompressedPointCloudDescriptors, kSceneUpdateDescriptors,
    kGridDescriptors;
}  // namespace detail

namespace {

// Protobuf's wire format (protobuf.dev, "Encoding"): proto3 leaves out fields at their
// default, as protobuf's own encoders do.
class Proto {
 public:
  void varint(int field, uint64_t value) {
    if (value == 0) return;
    key(field, 0);
    raw(value);
  }
  void fixed32(int field, uint32_t value) {
    if (value == 0) return;
    key(field, 5);
    for (int i = 0; i < 4; ++i) out_.push_back(static_cast<char>((value >> (8 * i)) & 0xff));
  }
  void float64(int field, double value) {
    if (value == 0) return;  // +0.0 is the default; -0.0 keeps its sign bit
    uint64_t bits;
    std::memcpy(&bits, &value, sizeof bits);
    if (bits == 0) return;
    key(field, 1);
    for (int i = 0; i < 8; ++i) out_.push_back(static_cast<char>((bits >> (8 * i)) & 0xff));
  }
  void bytes(int field, std::string_view value) {
    if (value.empty()) return;
    key(field, 2);
    raw(value.size());
    out_.append(value);
  }
  // An embedded message: present even when empty (it is then its default, as a reader sees it).
  void message(int field, const Proto& value) {
    key(field, 2);
    raw(value.out_.size());
    out_.append(value.out_);
  }
  const std::string& str() const { return out_; }
  std::string take() { return std::move(out_); }

 private:
  void key(int field, int wire_type) { raw((static_cast<uint64_t>(field) << 3) | wire_type); }
  void raw(uint64_t value) {
    while (value >= 0x80) {
      out_.push_back(static_cast<char>((value & 0x7f) | 0x80));
      value >>= 7;
    }
    out_.push_back(static_cast<char>(value));
  }
  std::string out_;
};

Proto timestamp(int64_t stamp_ns) {
  Proto t;  // google.protobuf.Timestamp: seconds, nanos in [0, 1e9)
  int64_t seconds = stamp_ns / 1000000000, nanos = stamp_ns % 1000000000;
  if (nanos < 0) nanos += 1000000000, --seconds;
  t.varint(1, static_cast<uint64_t>(seconds));
  t.varint(2, static_cast<uint64_t>(nanos));
  return t;
}

Proto vector3(const common::Vec3& v) {
  Proto p;  // foxglove.Vector3 and foxglove.Point3 alike
  p.float64(1, v.x());
  p.float64(2, v.y());
  p.float64(3, v.z());
  return p;
}

Proto quaternion(const common::Quat& q) {
  Proto p;
  p.float64(1, q.x());
  p.float64(2, q.y());
  p.float64(3, q.z());
  p.float64(4, q.w());
  return p;
}

Proto pose(const common::Rigid3& T) {
  Proto p;
  p.message(1, vector3(T.translation));
  p.message(2, quaternion(T.rotation));
  return p;
}

Proto packedField(std::string_view name, uint32_t offset, int numeric_type) {
  Proto p;  // foxglove.PackedElementField
  p.bytes(1, name);
  p.fixed32(2, offset);
  p.varint(3, static_cast<uint64_t>(numeric_type));
  return p;
}

constexpr int kUint8 = 1, kInt8 = 2, kFloat32 = 7;

}  // namespace

std::string_view schemaName(Schema schema) {
  switch (schema) {
    case Schema::kFrameTransform:
      return "foxglove.FrameTransform";
    case Schema::kPosesInFrame:
      return "foxglove.PosesInFrame";
    case Schema::kPointCloud:
      return "foxglove.PointCloud";
    case Schema::kCompressedPointCloud:
      return "foxglove.CompressedPointCloud";
    case Schema::kSceneUpdate:
      return "foxglove.SceneUpdate";
    case Schema::kGrid:
      return "foxglove.Grid";
  }
  return {};
}

std::string base64(std::string_view bytes) {
  static constexpr char kAlphabet[] =
      "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  std::string out;
  out.reserve((bytes.size() + 2) / 3 * 4);
  for (size_t i = 0; i < bytes.size(); i += 3) {
    const size_t n = std::min<size_t>(3, bytes.size() - i);
    uint32_t group = 0;
    for (size_t k = 0; k < 3; ++k) {
      group = (group << 8) | (k < n ? static_cast<uint8_t>(bytes[i + k]) : 0u);
    }
    for (size_t k = 0; k < 4; ++k) {
      out.push_back(k <= n ? kAlphabet[(group >> (18 - 6 * k)) & 63] : '=');
    }
  }
  return out;
}

std::string_view descriptorSet(Schema schema) {
  switch (schema) {
    case Schema::kFrameTransform:
      return detail::kFrameTransformDescriptors;
    case Schema::kPosesInFrame:
      return detail::kPosesInFrameDescriptors;
    case Schema::kPointCloud:
      return detail::kPointCloudDescriptors;
    case Schema::kCompressedPointCloud:
      return detail::kCompressedPointCloudDescriptors;
    case Schema::kSceneUpdate:
      return detail::kSceneUpdateDescriptors;
    case Schema::kGrid:
      return detail::kGridDescriptors;
  }
  return {};
}

std::string frameTransform(int64_t stamp_ns, std::string_view parent, std::string_view child,
                           const common::Rigid3& T_parent_child) {
  Proto p;
  p.message(1, timestamp(stamp_ns));
  p.bytes(2, parent);
  p.bytes(3, child);
  p.message(4, vector3(T_parent_child.translation));
  p.message(5, quaternion(T_parent_child.rotation));
  return p.take();
}

std::string posesInFrame(int64_t stamp_ns, std::string_view frame,
                         const std::vector<common::Rigid3>& poses) {
  Proto p;
  p.message(1, timestamp(stamp_ns));
  p.bytes(2, frame);
  for (const auto& T : poses) p.message(3, pose(T));
  return p.take();
}

std::string pointCloud(int64_t stamp_ns, std::string_view frame, const common::Rigid3& T,
                       const common::PointCloud& cloud) {
  const bool intensity = cloud.hasIntensity() && cloud.intensity.size() == cloud.size();
  const uint32_t stride = intensity ? 13 : 12;
  std::string data(cloud.size() * stride, '\0');
  for (size_t i = 0; i < cloud.size(); ++i) {
    std::memcpy(data.data() + i * stride, cloud.points[i].data(), 12);  // little-endian floats
    if (intensity) data[i * stride + 12] = static_cast<char>(cloud.intensity[i]);
  }
  Proto p;
  p.message(1, timestamp(stamp_ns));
  p.bytes(2, frame);
  p.message(3, pose(T));
  p.fixed32(4, stride);
  p.message(5, packedField("x", 0, kFloat32));
  p.message(5, packedField("y", 4, kFloat32));
  p.message(5, packedField("z", 8, kFloat32));
  if (intensity) p.message(5, packedField("intensity", 12, kUint8));
  p.bytes(6, data);
  return p.take();
}

std::string compressedPointCloud(int64_t stamp_ns, std::string_view frame, const common::Rigid3& T,
                                 std::string_view data, std::string_view format) {
  Proto p;
  p.message(1, timestamp(stamp_ns));
  p.bytes(2, frame);
  p.message(3, pose(T));
  p.bytes(4, data);
  p.bytes(5, format);
  return p.take();
}

std::string grid(int64_t stamp_ns, std::string_view frame, const common::Rigid3& origin,
                 uint32_t columns, double cell_m, const std::vector<int8_t>& cells) {
  Proto p, cell_size;
  cell_size.float64(1, cell_m);
  cell_size.float64(2, cell_m);
  p.message(1, timestamp(stamp_ns));
  p.bytes(2, frame);
  p.message(3, pose(origin));
  p.fixed32(4, columns);
  p.message(5, cell_size);
  p.fixed32(6, columns);  // row stride, bytes
  p.fixed32(7, 1);        // cell stride
  p.message(8, packedField("occupancy", 0, kInt8));
  p.bytes(9, std::string_view(reinterpret_cast<const char*>(cells.data()), cells.size()));
  return p.take();
}

std::string sceneEntityField(int64_t stamp_ns, std::string_view frame, const Entity& entity) {
  const Proto stamp = timestamp(stamp_ns);
  const Proto identity = quaternion(common::Quat::Identity());
  Proto e;  // foxglove.SceneEntity
  e.message(1, stamp);
  e.bytes(2, frame);
  e.bytes(3, entity.id);
  for (const auto& [key, value] : entity.metadata) {
    Proto pair;
    pair.bytes(1, key);
    pair.bytes(2, value);
    e.message(6, pair);
  }
  for (const Cube& cube : entity.cubes) {
    Proto c, where, size, color;  // foxglove.CubePrimitive
    where.message(1, vector3(cube.centre));
    where.message(2, identity);
    size.float64(1, cube.size);
    size.float64(2, cube.size);
    size.float64(3, cube.size);
    color.float64(1, cube.r);
    color.float64(2, cube.g);
    color.float64(3, cube.b);
    color.float64(4, cube.a);
    c.message(1, where);
    c.message(2, size);
    c.message(3, color);
    e.message(8, c);
  }
  Proto field;
  field.message(2, e);
  return field.take();
}

std::string sceneDeletionField(int64_t stamp_ns, std::string_view id) {
  Proto deletion;  // foxglove.SceneEntityDeletion, type MATCHING_ID (0, the default)
  deletion.message(1, timestamp(stamp_ns));
  deletion.bytes(3, id);
  Proto field;
  field.message(1, deletion);
  return field.take();
}

std::string sceneUpdate(int64_t stamp_ns, std::string_view frame,
                        const std::vector<Entity>& entities,
                        const std::vector<std::string>& deleted) {
  std::string update;
  for (const std::string& id : deleted) update += sceneDeletionField(stamp_ns, id);
  for (const Entity& entity : entities) update += sceneEntityField(stamp_ns, frame, entity);
  return update;
}

}  // namespace stereomap::foxglove
