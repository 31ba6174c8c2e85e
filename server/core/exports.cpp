#include "server/core/exports.hpp"

#include <algorithm>
#include <sstream>

#include "common/png.hpp"
#include "common/time.hpp"
#include "common/trajectory.hpp"
#include "server/core/occupancy_grid.hpp"

namespace stereomap::core {

common::Result<ExportFile> exportSession(const Session& session, const std::string& id,
                                         const ExportRequest& request) {
  const std::string binary = "application/octet-stream";
  const std::string name = id + "." + request.format;
  if (request.format == "bt" || request.format == "ot") {
    auto map = request.format == "bt" ? session.mapBinary() : session.mapFull();
    if (!map) return map.error();
    return ExportFile{std::move(*map), binary, name};
  }
  if (request.format == "ply") return ExportFile{occupiedPly(session), binary, name};
  if (request.format == "png") {
    auto png = occupancyPng(session, request.z_min, request.z_max, request.scale);
    if (!png) return png.error();
    return ExportFile{std::move(*png), "image/png", name};
  }
  if (request.format == "pgm" || request.format == "yaml") {
    auto bt = session.mapBinary();
    if (!bt) return bt.error();
    std::istringstream in(*bt);
    auto map = fusion::OccupancyMap::load(in);
    if (!map) return map.error();
    auto grid = occupancyGrid(**map, request.z_min, request.z_max);
    if (!grid) return grid.error();
    if (request.format == "pgm")
      return ExportFile{gridPgm(*grid), "image/x-portable-graymap", name};
    const std::string image = request.grid_image.empty() ? id + ".pgm" : request.grid_image;
    return ExportFile{gridYaml(*grid, image), "application/yaml", name};
  }
  if (request.format == "tum") {
    const auto vehicles = session.status().vehicles;
    const std::string& wanted = request.vehicle;
    if (!wanted.empty() && std::find(vehicles.begin(), vehicles.end(), wanted) == vehicles.end()) {
      return common::makeError(common::ErrorCode::kNotFound,
                               "session '" + id + "' has no vehicle '" + wanted + "'");
    }
    const std::string chosen = !wanted.empty() ? wanted : vehicles.empty() ? "" : vehicles[0];
    return ExportFile{trajectoryTum(session, chosen), "text/plain",
                      id + (chosen.empty() ? "" : "-" + chosen) + ".tum"};
  }
  return common::makeError(
      common::ErrorCode::kInvalidArgument,
      "unknown export format '" + request.format + "' (bt, ot, ply, png, pgm, yaml, tum)");
}

std::string occupiedPly(const Session& session) {
  const auto voxels = session.occupiedVoxels();
  const double resolution = session.tiles().resolution();
  std::ostringstream out;
  out << "ply\nformat binary_little_endian 1.0\ncomment stereomap session " << session.id()
      << ", occupied voxel centres, resolution " << resolution << " m\nelement vertex "
      << voxels.size() << "\nproperty float x\nproperty float y\nproperty float z\n"
      << "end_header\n";
  for (const auto& v : voxels) {
    const float xyz[3] = {static_cast<float>((v.x + 0.5) * resolution),
                          static_cast<float>((v.y + 0.5) * resolution),
                          static_cast<float>((v.z + 0.5) * resolution)};
    out.write(reinterpret_cast<const char*>(xyz), sizeof(xyz));
  }
  return out.str();
}

common::Result<std::string> occupancyPng(const Session& session, double z_min, double z_max,
                                         int pixels_per_voxel) {
  const double resolution = session.tiles().resolution();
  std::vector<fusion::VoxelIndex> band;
  for (const auto& v : session.occupiedVoxels()) {
    const double z = (v.z + 0.5) * resolution;
    if (z >= z_min && z <= z_max) band.push_back(v);
  }
  if (band.empty()) {
    return common::makeError(common::ErrorCode::kNotFound,
                             "no occupied voxels in that height band");
  }
  int32_t x0 = band[0].x, x1 = x0, y0 = band[0].y, y1 = y0;
  for (const auto& v : band) {
    x0 = std::min(x0, v.x), x1 = std::max(x1, v.x);
    y0 = std::min(y0, v.y), y1 = std::max(y1, v.y);
  }
  // North up: the first row is the largest y. Each voxel becomes a square of
  // pixels_per_voxel pixels.
  const uint32_t scale = static_cast<uint32_t>(std::max(1, pixels_per_voxel));
  const uint64_t width64 = static_cast<uint64_t>(x1 - x0 + 1) * scale;
  const uint64_t height64 = static_cast<uint64_t>(y1 - y0 + 1) * scale;
  if (width64 * height64 > kMaxPngPixels) {
    return common::makeError(common::ErrorCode::kTooLarge,
                             "the image would be " + std::to_string(width64) + " x " +
                                 std::to_string(height64) + " pixels (at most " +
                                 std::to_string(kMaxPngPixels >> 20) +
                                 " Mpx): ask for a smaller scale");
  }
  const auto width = static_cast<uint32_t>(width64);
  const auto height = static_cast<uint32_t>(height64);
  std::vector<uint8_t> pixels(static_cast<size_t>(width) * height, 0);
  for (const auto& v : band) {
    const size_t column = static_cast<size_t>(v.x - x0) * scale;
    const size_t row = static_cast<size_t>(y1 - v.y) * scale;
    for (uint32_t dy = 0; dy < scale; ++dy) {
      std::fill_n(pixels.begin() + static_cast<std::ptrdiff_t>((row + dy) * width + column), scale,
                  uint8_t{255});
    }
  }
  std::string png = common::encodeGreyPng(pixels, width, height);
  if (png.empty()) return common::makeError(common::ErrorCode::kIo, "the PNG could not be encoded");
  return png;
}

std::string trajectoryTum(const Session& session, const std::string& vehicle_id) {
  common::Trajectory poses;
  for (const auto& pose : session.trajectory()) {
    if (!vehicle_id.empty() && pose.vehicle_id != vehicle_id) continue;
    poses.push_back({common::nsToSeconds(pose.stamp_ns), pose.T_map_body});
  }
  return common::tumText(poses);
}

}  // namespace stereomap::core
