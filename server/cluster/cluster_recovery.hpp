// A session fused again from what the cluster's database holds of it: by a server taking it
// over, and offline (tests, tools) to check a live map against its journal.
#pragma once

#include <cstddef>

#include "common/result.hpp"
#include "server/cluster/cluster_db.hpp"
#include "server/cluster/cluster_journal.hpp"
#include "server/core/map_server.hpp"

namespace stereomap::cluster {

// Creates `owned.session` in `server` at its resolution (read-only when `owned` is) and replays
// `stored` (from journal.read(), moved from) into it, in the file store's order (store_admin.cpp):
// poses and corrections, the snapshot when it holds the newest correction, then frames and events
// in journal order (frames read again from `journal` when the snapshot cannot be used); counts the
// frames and poses taken. The frames are queued for fusion before any live one can be (a server
// takes samples for the session only after this returns), so a server need not wait for them:
// `wait_until_fused` for offline use (exports, checks).
common::Status recoverSession(core::MapServer& server, ClusterJournal& journal,
                              const Ownership& owned, StoredSession& stored, size_t& frames,
                              size_t& poses, bool wait_until_fused);

}  // namespace stereomap::cluster
