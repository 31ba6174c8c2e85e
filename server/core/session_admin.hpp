// What operators do with stored sessions: open one read-only, close it into the store,
// delete it, merge two into a new one. The store implements it (server/store); the API
// (server/core/api.hpp) and the offline CLI only call it.
#pragma once

#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "common/geometry.hpp"
#include "common/result.hpp"
#include "server/core/session.hpp"
#include "server/core/validate.hpp"

namespace stereomap::core {

// One session of a merge, and where its map frame goes in the merged session's.
struct MergeSource {
  std::string id;  // an existing session (loaded or closed)
  common::Rigid3 T_into_source = common::Rigid3::identity();
};

struct MergeRequest {
  // Two or more sessions; the first's frame is the merged session's (its transform is the
  // identity). A site is such a merge, each session registered into the first's frame.
  std::vector<MergeSource> sources;
  std::string into;  // the new session's id
  // What made it, kept with the merged session and shown in its status ("origin"): a JSON
  // object as text ({"site": [...]}), or "" for none.
  std::string origin;

  // The usual merge: `second` moved by T_first_second (identity: the same frame).
  static MergeRequest pair(std::string first, std::string second, std::string into,
                           const common::Rigid3& T_first_second = common::Rigid3::identity()) {
    return {{{std::move(first), common::Rigid3::identity()}, {std::move(second), T_first_second}},
            std::move(into),
            ""};
  }
  // Why it cannot be merged as asked (fewer than two sessions, a bad or repeated id), or "".
  std::string problem() const {
    if (sources.size() < 2) return "merge needs two or more sessions";
    if (sources.size() > kMaxSources) {
      return "merge takes at most " + std::to_string(kMaxSources) + " sessions";
    }
    for (size_t i = 0; i < sources.size(); ++i) {
      if (!isValidId(sources[i].id)) return badId(sources[i].id);
      for (size_t j = 0; j < i; ++j) {
        if (sources[j].id == sources[i].id) {
          return "merge needs different sessions ('" + sources[i].id + "' twice)";
        }
      }
    }
    return isValidId(into) ? "" : badId(into);
  }
  // A site of more would fuse for long; split it.
  static constexpr size_t kMaxSources = 64;

 private:
  static std::string badId(const std::string& id) {
    return "session id '" + id.substr(0, 80) + "' is not 1-64 of [A-Za-z0-9._-]";
  }
};

class SessionAdmin {
 public:
  virtual ~SessionAdmin() = default;
  // Sessions kept in the store but not loaded (state "closed"), by id. Asked on every
  // listing (REST, viewers): answered from memory.
  virtual std::vector<SessionStatus> closedSessions() const = 0;
  // Loads a closed session read-only (snapshot + journal replay), with its trajectory.
  // kNotFound: no such session; kConflict: already loaded.
  virtual common::Status open(const std::string& id) = 0;
  // Saves a loaded session (map, trajectory, snapshot) and unloads it; later samples for
  // it are refused. kNotFound / kConflict (already closed).
  virtual common::Status close(const std::string& id) = 0;
  // Deletes a session that is not live (closed, ended or opened read-only) from the store.
  virtual common::Status remove(const std::string& id) = 0;
  // Writes a new, closed session whose journal holds every source's frames (each moved by
  // its transform; a vehicle renamed where an earlier source has one of its name) and opens
  // it read-only.
  virtual common::Status merge(const MergeRequest& request) = 0;
  // The session as it was at `until_ns` (sample stamps, ns since the epoch): a new read-only
  // Session, loaded nowhere, fused from the journal's frames and poses stamped no later
  // (the time slider's replay). Any stored session with a journal, loaded or not; it takes
  // as long as fusing those frames. kNotFound: no such session in the store.
  virtual common::Result<std::shared_ptr<Session>> replay(const std::string& id,
                                                          int64_t until_ns) const = 0;

  // In a cluster (server/cluster): the sessions other servers serve, for listings (state
  // live or ended, `server` naming where; their counts are that server's to tell). None on a
  // single server.
  virtual std::vector<SessionStatus> remoteSessions() const { return {}; }
  // In a cluster: the address (host:port) of the server that serves session `id`, for the
  // proxy's routing (GET /api/cluster/route); nullopt on a single server, or when no live
  // server serves it.
  virtual std::optional<std::string> routeTo(const std::string& /*id*/) const {
    return std::nullopt;
  }
  // In a cluster: this server's own address (routes for unknown sessions go there).
  virtual std::optional<std::string> selfAddress() const { return std::nullopt; }
};

}  // namespace stereomap::core
