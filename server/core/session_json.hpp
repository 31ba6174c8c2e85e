// A session's status as JSON, written and read in this one place: REST (GET /api/sessions and
// /api/sessions/{id}), the viewers' "session" and "sessions" messages, the store's
// session.json and `stereomap-store list --json` / `show` all use this shape (docs/PROTOCOL.md).
#pragma once

#include <string>

#include <nlohmann/json.hpp>

#include "server/core/session.hpp"

namespace stereomap::core {

// kAll: every field. kCatalog: those the store's catalog keeps (id, vehicle, vehicles, state,
// resolution, frames, occupied_voxels, bounds), for listings read from it.
enum class SessionFields { kAll, kCatalog };

nlohmann::json sessionObject(const SessionStatus& status,
                             SessionFields fields = SessionFields::kAll);
// A box as {"min": [x, y, z], "max": [x, y, z]} (metres), null when empty: a session's
// bounds, and the viewers' map summary.
nlohmann::json boundsJson(const common::Box3& bounds);

// sessionObject as text, with "type": message_type when given (a viewer message).
std::string sessionJson(const SessionStatus& status, const char* message_type = nullptr);

// What sessionObject wrote, read back (a stored session.json): counts, vehicles, resolution,
// bounds and the state (closed, opened and ended sessions all count as ended, and so does one
// whose document has no state). A field that is missing or of the wrong type keeps its
// default; `id` is the caller's (a directory's name, validated), never the document's.
SessionStatus sessionFromJson(const std::string& id, const nlohmann::json& doc);

}  // namespace stereomap::core
