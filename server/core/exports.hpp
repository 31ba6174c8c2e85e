// A session's map and trajectory as files: OctoMap (.bt, .ot), PLY, a top-down PNG and TUM,
// for REST downloads (server/core/api), `stereomap-store export` and the store's saved
// files. Everything here reads the session (its tiles, trajectory and forked serialisation);
// nothing of it lives in Session, which therefore knows no image or file formats.
#pragma once

#include <string>

#include "common/result.hpp"
#include "server/core/session.hpp"

namespace stereomap::core {

// format "bt", "ot", "ply", "png" (the height band z_min..z_max, scale pixels per voxel),
// "pgm" and "yaml" (the band as a 2D occupancy grid, map_server's files: occupancy_grid.hpp;
// the YAML names the image {id}.pgm) or "tum" (one vehicle: the given one, else the session's
// first). kNotFound names what is
// missing (the vehicle, or voxels in the band); the caller checks the request's values.
struct ExportRequest {
  std::string format;
  double z_min = -1e9, z_max = 1e9;
  int scale = 1;
  std::string vehicle;
  std::string grid_image;  // yaml: the image's file name ("": {id}.pgm)
};
struct ExportFile {
  std::string content;
  std::string content_type;
  std::string name;  // REST's download name: {id}.{format}, {id}-{vehicle}.tum
};
common::Result<ExportFile> exportSession(const Session& session, const std::string& id,
                                         const ExportRequest& request);

// Binary PLY of the occupied voxels' centres (map frame, metres).
std::string occupiedPly(const Session& session);

// A top-down PNG of the occupied voxels with centres in [z_min, z_max] (one pixel per voxel,
// or a square of pixels_per_voxel; white occupied, black not); pixel (0, 0) is the voxel with
// the smallest x and largest y. kNotFound when nothing is occupied in the band; kTooLarge
// above kMaxPngPixels (a request cannot make the server allocate gigabytes).
constexpr size_t kMaxPngPixels = 64u << 20;
common::Result<std::string> occupancyPng(const Session& session, double z_min, double z_max,
                                         int pixels_per_voxel = 1);

// TUM lines "t tx ty tz qx qy qz qw" of one vehicle's poses (all vehicles' when empty), as
// corrected.
std::string trajectoryTum(const Session& session, const std::string& vehicle_id = "");

}  // namespace stereomap::core
