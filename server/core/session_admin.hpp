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

namespace stereomap::core {

struct MergeRequest {
  std::string first, second;  // existing sessions (loaded or closed)
  std::string into;           // the new session's id
  // Maps the second session's map frame into the first's (identity: same frame).
  common::Rigid3 T_first_second;
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
  // Writes a new, closed session whose journal holds both sessions' frames (the second's
  // moved by the transform; its vehicles renamed where they clash) and opens it read-only.
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
