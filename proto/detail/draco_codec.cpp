// Draco's point-cloud coder: positions quantised over the bounding cube, 8-bit intensity as a
// generic attribute.
#include <draco/compression/decode.h>
#include <draco/compression/encode.h>
#include <draco/point_cloud/point_cloud_builder.h>

#include <cmath>
#include <cstring>
#include <optional>
#include <string>

#include "proto/detail/codecs.hpp"

namespace stereomap::proto::detail {

using common::ErrorCode;
using common::makeError;
using common::PointCloud;
using common::Result;

Result<std::vector<uint8_t>> encodeDraco(const PointCloud& cloud,
                                         const CloudCodecOptions& options) {
  if (cloud.size() == 0) return std::vector<uint8_t>{};  // an empty cloud: an empty payload
  draco::PointCloudBuilder builder;
  builder.Start(static_cast<draco::PointIndex::ValueType>(cloud.size()));
  const int position =
      builder.AddAttribute(draco::GeometryAttribute::POSITION, 3, draco::DT_FLOAT32);
  builder.SetAttributeValuesForAllPoints(position, cloud.points.data(), sizeof(common::Vec3f));
  if (cloud.hasIntensity()) {
    const int intensity =
        builder.AddAttribute(draco::GeometryAttribute::GENERIC, 1, draco::DT_UINT8);
    builder.SetAttributeValuesForAllPoints(intensity, cloud.intensity.data(), 1);
  }
  std::unique_ptr<draco::PointCloud> draco_cloud = builder.Finalize(false);
  if (!draco_cloud)
    return makeError(ErrorCode::kInvalidArgument, "Draco could not build the cloud");

  draco::Encoder encoder;
  encoder.SetAttributeQuantization(draco::GeometryAttribute::POSITION, options.quantization_bits);
  encoder.SetSpeedOptions(options.draco_speed, options.draco_speed);
  encoder.SetEncodingMethod(options.draco_kd_tree ? draco::POINT_CLOUD_KD_TREE_ENCODING
                                                  : draco::POINT_CLOUD_SEQUENTIAL_ENCODING);
  draco::EncoderBuffer buffer;
  const draco::Status status = encoder.EncodePointCloudToBuffer(*draco_cloud, &buffer);
  if (!status.ok()) {
    return makeError(ErrorCode::kInvalidArgument,
                     std::string("Draco encoding failed: ") + status.error_msg());
  }
  return std::vector<uint8_t>(buffer.data(), buffer.data() + buffer.size());
}

namespace {

// Draco's header as its 2.3 bitstream writes it: "DRACO", major and minor version, encoder
// type, method, 16-bit flags; a point cloud's point count follows as 32 bits, then the number
// of attribute decoders (8 bits), the number of attributes (a varint) and each attribute's
// descriptor: type, data type, components, normalised, a varint id.
constexpr size_t kHeaderBytes = 15;
constexpr uint8_t kPointCloudType = 0;  // draco::POINT_CLOUD
struct Descriptor {
  uint8_t type, data_type, components;
};
// What encodeDraco writes, and all Draco may be given: positions, and intensity when the
// message says so. Draco sizes a buffer of point count x components per attribute before it
// reads a point, so these bound what a payload can make it allocate (a few hundred bytes of
// descriptors could otherwise ask for 40 GB at the server's point limit).
constexpr Descriptor kPosition{0, 9, 3};   // POSITION, DT_FLOAT32, 3
constexpr Descriptor kIntensity{4, 2, 1};  // GENERIC, DT_UINT8, 1

std::optional<common::Error> checkHeader(std::span<const uint8_t> payload,
                                         const CloudPayloadInfo& info) {
  auto corrupt = [](const std::string& what) {
    return common::Error{ErrorCode::kCorrupt, "Draco payload: " + what};
  };
  if (payload.size() < kHeaderBytes || std::memcmp(payload.data(), "DRACO", 5) != 0) {
    return corrupt("no Draco header");
  }
  // Only the version Draco 1.5 writes: older ones take other paths (one of them filled 6.8 GB
  // for a fuzzed 10-point cloud).
  if (payload[5] != 2 || payload[6] != 3) {
    return corrupt("bitstream version " + std::to_string(payload[5]) + "." +
                   std::to_string(payload[6]) + ", not 2.3");
  }
  if (payload[7] != kPointCloudType) return corrupt("a mesh, not a point cloud");
  if (payload[9] != 0 || payload[10] != 0) return corrupt("flags or metadata");
  uint32_t count = 0;
  std::memcpy(&count, payload.data() + 11, 4);
  if (count != info.point_count) {
    return common::Error{ErrorCode::kConflict, "Draco payload holds " + std::to_string(count) +
                                                   " points, point_count says " +
                                                   std::to_string(info.point_count)};
  }
  const size_t attributes = info.has_intensity ? 2 : 1;
  size_t at = kHeaderBytes;
  if (payload.size() < at + 2 || payload[at] != 1 || payload[at + 1] != attributes) {
    return corrupt("not one attribute decoder with " + std::to_string(attributes) +
                   " attribute(s) (intensity as the message says)");
  }
  at += 2;
  const Descriptor allowed[] = {kPosition, kIntensity};
  for (size_t i = 0; i < attributes; ++i) {
    const Descriptor& expected = allowed[i];
    // type, data type, components, normalised (0), and a one-byte varint id
    if (payload.size() < at + 5 || payload[at] != expected.type ||
        payload[at + 1] != expected.data_type || payload[at + 2] != expected.components ||
        payload[at + 3] != 0 || payload[at + 4] >= 0x80) {
      return corrupt("an attribute other than positions and 8-bit intensity");
    }
    at += 5;
  }
  return std::nullopt;
}

}  // namespace

Result<PointCloud> decodeDraco(std::span<const uint8_t> payload, const CloudPayloadInfo& info) {
  PointCloud cloud;
  if (payload.empty() && info.point_count == 0) return cloud;
  if (auto bad = checkHeader(payload, info)) return *bad;
  draco::DecoderBuffer buffer;
  buffer.Init(reinterpret_cast<const char*>(payload.data()), payload.size());
  draco::Decoder decoder;
  auto decoded = decoder.DecodePointCloudFromBuffer(&buffer);
  if (!decoded.ok()) {
    return makeError(ErrorCode::kCorrupt,
                     std::string("Draco payload does not decode: ") + decoded.status().error_msg());
  }
  const std::unique_ptr<draco::PointCloud> draco_cloud = std::move(decoded).value();
  const draco::PointAttribute* position =
      draco_cloud->GetNamedAttribute(draco::GeometryAttribute::POSITION);
  if (position == nullptr || position->num_components() != 3) {
    return makeError(ErrorCode::kCorrupt, "Draco payload has no 3D position attribute");
  }
  const draco::PointAttribute* intensity =
      draco_cloud->GetNamedAttribute(draco::GeometryAttribute::GENERIC);
  if (intensity != nullptr && intensity->num_components() != 1) {
    return makeError(ErrorCode::kCorrupt, "Draco payload's intensity is not one component");
  }

  const uint32_t n = draco_cloud->num_points();
  cloud.points.resize(n);
  if (intensity != nullptr) cloud.intensity.resize(n);
  for (draco::PointIndex i(0); i < n; ++i) {
    float xyz[3];
    if (!position->ConvertValue<float, 3>(position->mapped_index(i), xyz)) {
      return makeError(ErrorCode::kCorrupt, "Draco position value cannot be read");
    }
    if (!std::isfinite(xyz[0]) || !std::isfinite(xyz[1]) || !std::isfinite(xyz[2])) {
      return makeError(ErrorCode::kCorrupt, "Draco payload decodes to a non-finite point");
    }
    cloud.points[i.value()] = common::Vec3f(xyz[0], xyz[1], xyz[2]);
    if (intensity != nullptr) {
      uint8_t value = 0;
      intensity->ConvertValue<uint8_t, 1>(intensity->mapped_index(i), &value);
      cloud.intensity[i.value()] = value;
    }
  }
  return cloud;
}

}  // namespace stereomap::proto::detail
