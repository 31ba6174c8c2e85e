// Where tests find the shared real data sets (../shared/data), and a skip with a message
// when a data set is absent (CI and users may run without it).
#pragma once

#include <gtest/gtest.h>

#include <filesystem>

namespace stereomap::testing {
inline const std::filesystem::path kDataDir = STEREOMAP_DATA_DIR;
}  // namespace stereomap::testing

#define STEREOMAP_SKIP_WITHOUT(path)  \
  if (!std::filesystem::exists(path)) \
  GTEST_SKIP() << "data not found: " << (path).string() << " (../shared/data is absent)"
