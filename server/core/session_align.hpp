// Two sessions' maps aligned (the second's frame into the first's: x_first = T x_second),
// for POST /api/sessions/align, merges with "align": "auto" and stereomap-store. A session
// the server has not loaded is opened read-only first, as a viewer opening it would.
#pragma once

#include <functional>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>

#include "common/result.hpp"
#include "server/align/map_align.hpp"
#include "server/core/map_server.hpp"
#include "server/core/session_admin.hpp"

namespace stereomap::core {

// The session's map as it is now (every queued frame fused). kNotFound: no such session.
common::Result<std::unique_ptr<fusion::OccupancyMap>> sessionMap(const MapServer& server,
                                                                 SessionAdmin* admin,
                                                                 const std::string& id);

// Where a session's map comes from: sessionMap() on a server or a store folder, a replay
// of a cluster's journal in stereomap-store --cluster.
using SessionMapSource =
    std::function<common::Result<std::unique_ptr<fusion::OccupancyMap>>(const std::string& id)>;

// The second session's map aligned onto the first's (an error names the session at fault).
common::Result<align::Alignment> alignSessions(const SessionMapSource& map_of,
                                               const std::string& first, const std::string& second,
                                               const align::AlignOptions& options);

// {"first", "second", "found", "line", and either "transform": [tx, ty, tz, qx, qy, qz, qw],
// "overlap", "rmse_m", "confidence", ... or "reason"}.
nlohmann::json alignmentJson(const std::string& first, const std::string& second,
                             const align::Alignment& alignment);

}  // namespace stereomap::core
