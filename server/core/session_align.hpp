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

// A rigid transform as [tx, ty, tz, qx, qy, qz, qw] (a unit quaternion, qw >= 0).
nlohmann::json transformJson(const common::Rigid3& T);

// {"first", "second", "found", "line", and either "transform": [tx, ty, tz, qx, qy, qz, qw],
// "overlap", "rmse_m", "confidence", ... or "reason"}.
nlohmann::json alignmentJson(const std::string& first, const std::string& second,
                             const align::Alignment& alignment);

// A site: flights of one place, each session registered into the first one's frame (the
// site's), and merged into one session that keeps every transform (its origin's "site").
struct SiteMember {
  std::string id;
  bool registered = false;
  std::string onto;  // the registered session it was aligned onto ("" for the first)
  common::Rigid3 T_site_session = common::Rigid3::identity();
  align::Alignment alignment;  // onto `onto` (found), or the last refusal
  std::string reason;          // why it was left out ("" when registered)
};

struct SitePlan {
  std::vector<SiteMember> members;  // in the order given; the first is the site's frame
  size_t registered() const;
  // {"sessions": [{"session", "onto", "transform", "overlap", "rmse_m"}, ...],
  //  "left_out": [{"session", "reason"}, ...]}: what the site session keeps and shows.
  nlohmann::json json() const;
  // The merge that makes the site `into`: the registered sessions, each moved by its
  // transform, and the origin {"site": json()}.
  MergeRequest mergeRequest(const std::string& into) const;
};

// "site S: B: t tx ty tz q qx qy qz qw, onto A (overlap O%, rmse E m)" (B's frame into the
// site's), "site S: A: the site's frame", or "site S: X: left out (reason)".
std::string siteMemberLine(const std::string& site, const SiteMember& member);

// Registers sessions[1..] into sessions[0]'s frame with no hint: each is aligned onto a
// session already registered (the first, then the others in the order they joined) until
// one alignment is found, and takes that one's transform composed with it; passes repeat
// while any joins, so a flight that overlaps only a later one is registered too, whatever
// the order given. A session that aligns onto none is left out with the reason (never
// placed by a guess). `joined` is told of each member as it is decided. Errors: a session
// that cannot be read; fewer than two sessions, or one named twice (kInvalidArgument).
common::Result<SitePlan> planSite(const SessionMapSource& map_of,
                                  const std::vector<std::string>& sessions,
                                  const align::AlignOptions& options,
                                  const std::function<void(const SiteMember&)>& joined = {});

}  // namespace stereomap::core
