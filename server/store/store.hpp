// Where sessions are kept on disk: one directory per session under the store root, with
// the map (map.bt), the trajectory (trajectory.tum) and a status file (session.json), each
// written atomically (temporary file + rename), so a crash never leaves half a file.
// The journal and snapshots are in session_journals.hpp; recovery and session management in
// store_admin.hpp.
#pragma once

#include <filesystem>

#include "common/result.hpp"
#include "server/core/session.hpp"

namespace stereomap::store {

class SessionStore {
 public:
  // Creates `root` if needed; fails with a message naming it when it is not a directory.
  static common::Result<SessionStore> open(const std::filesystem::path& root);
  // Whether a file can be written in the store now (a full disk: no, naming the cause).
  common::Status probe() const;
  // `closed`: the session is being closed into the store (session.json says so).
  common::Status save(const core::Session& session, bool closed = false) const;
  const std::filesystem::path& root() const { return root_; }

 private:
  explicit SessionStore(std::filesystem::path root) : root_(std::move(root)) {}
  std::filesystem::path root_;
};

}  // namespace stereomap::store
