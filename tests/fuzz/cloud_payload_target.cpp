// Fuzz target: a CloudFrame's payload as the server decodes it (proto::decodeCloud), in every
// encoding. The first byte picks the encoding and whether the message says it has intensity,
// the next four its point count (bounded as the server's IngestLimits bound it); the rest is
// the payload. Decoding must return a cloud of the stated shape or an error: never crash,
// read out of bounds or allocate without bound (run with -rss_limit_mb).
#include <cstdint>
#include <cstring>

#include "proto/cloud_codec.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace stereomap;
  if (size < 5) return 0;
  proto::CloudPayloadInfo info;
  info.encoding = static_cast<proto::CloudEncoding>(data[0] % 3);
  info.has_intensity = (data[0] & 4) != 0;
  std::memcpy(&info.point_count, data + 1, 4);
  info.point_count %= 1'000'001;  // the server's default IngestLimits::max_points
  const auto cloud = proto::decodeCloud({data + 5, size - 5}, info);
  if (cloud && info.encoding != proto::CloudEncoding::kDraco) {
    // Decoders that know the count must keep it (Draco's is checked by the server after).
    if (cloud->size() != info.point_count) __builtin_trap();
    if (cloud->hasIntensity() != info.has_intensity && info.point_count > 0) __builtin_trap();
  }
  return 0;
}
