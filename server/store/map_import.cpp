#include "server/store/map_import.hpp"

#include <fstream>
#include <sstream>

#include "server/fusion/occupancy_map.hpp"

namespace stereomap::store {

using common::ErrorCode;
using common::makeError;

common::Result<ImportableMap> readImportableMap(const std::filesystem::path& file) {
  std::ifstream in(file, std::ios::binary);
  if (!in) return makeError(ErrorCode::kNotFound, "cannot read " + file.string());
  auto map = fusion::OccupancyMap::load(in);
  if (!map) return makeError(map.error().code, file.string() + ": " + map.error().message);
  ImportableMap out;
  out.resolution = (*map)->resolution();
  if (out.resolution < 0.01 || out.resolution > 2.0) {
    return makeError(ErrorCode::kInvalidArgument,
                     file.string() + ": resolution " + std::to_string(out.resolution) +
                         " m is outside what the server fuses (0.01 .. 2 m)");
  }
  std::ostringstream ot;
  if (!(*map)->writeFull(ot)) return makeError(ErrorCode::kIo, "cannot convert the map");
  out.ot = ot.str();
  return out;
}

}  // namespace stereomap::store
