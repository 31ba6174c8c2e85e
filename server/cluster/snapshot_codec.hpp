// How the cluster keeps a map snapshot in its database: the .ot compressed with zstd (fast
// level), stored without PostgreSQL's own compression. A snapshot is megabytes of WAL the
// journal's commits would otherwise wait behind (measured: docs/BENCHMARKS.md, cluster).
#pragma once

#include <string>

#include "common/result.hpp"

namespace stereomap::cluster {

std::string packSnapshot(const std::string& ot);
// The .ot again; a row that is not a zstd frame is taken as a raw .ot. kCorrupt when the
// frame does not decompress.
common::Result<std::string> unpackSnapshot(const std::string& packed);

}  // namespace stereomap::cluster
