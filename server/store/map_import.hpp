// An OctoMap file (.bt or .ot) made ready to become a session: read whole and checked before
// anything is written anywhere (the file store's import, and the cluster's).
#pragma once

#include <filesystem>
#include <string>

#include "common/result.hpp"

namespace stereomap::store {

struct ImportableMap {
  double resolution = 0;
  std::string ot;  // the map in OctoMap's full format: a snapshot of label 0
};

// kNotFound: unreadable; the map's own errors (damage); kInvalidArgument: a resolution the
// server does not fuse (outside 0.01 .. 2 m).
common::Result<ImportableMap> readImportableMap(const std::filesystem::path& file);

}  // namespace stereomap::store
