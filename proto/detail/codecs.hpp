// The encodings behind proto/cloud_codec.hpp, one file each. Options and inputs arrive checked
// (bits in range, finite points, intensity count equal to the point count).
#pragma once

#include <cstdint>
#include <span>
#include <vector>

#include "common/point_cloud.hpp"
#include "common/result.hpp"
#include "proto/cloud_codec.hpp"

namespace stereomap::proto::detail {

common::Result<std::vector<uint8_t>> encodeDraco(const common::PointCloud& cloud,
                                                 const CloudCodecOptions& options);
// Checks Draco's header before Draco reads on: a point cloud without metadata, holding
// info.point_count points (Draco sizes its buffers by the count it reads: one flipped byte
// there made it fill 24 GiB).
common::Result<common::PointCloud> decodeDraco(std::span<const uint8_t> payload,
                                               const CloudPayloadInfo& info);

common::Result<std::vector<uint8_t>> encodeQuantZstd(const common::PointCloud& cloud,
                                                     const CloudCodecOptions& options);
common::Result<common::PointCloud> decodeQuantZstd(std::span<const uint8_t> payload,
                                                   const CloudPayloadInfo& info);

}  // namespace stereomap::proto::detail
