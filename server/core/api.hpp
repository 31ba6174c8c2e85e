// The server's HTTP API as plain functions of the MapServer (no networking here): REST
// answers for /healthz, /metrics and /api/sessions..., so the Beast layer only transports.
// See docs/PROTOCOL.md.
#pragma once

#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "server/core/exports.hpp"
#include "server/core/map_server.hpp"
#include "server/core/session_admin.hpp"

namespace stereomap::core {

struct HttpAnswer {
  int status = 200;
  std::string content_type = "application/json";
  std::string body;
  std::string filename;  // when set: offered as a download with this name
  std::string etag;      // when set: sent as ETag, with Cache-Control no-cache (revalidate)
  // With an ETag: the body at this URL never changes (a versioned tile), so any cache may keep
  // it for good: Cache-Control public, immutable.
  bool immutable = false;
  std::vector<std::pair<std::string, std::string>> headers;  // more response headers
};

// The body of every error answer, {"error": MESSAGE}: a message may quote request bytes, so
// invalid UTF-8 in it is replaced, never thrown.
std::string errorBody(const std::string& message);

// True for the paths answerApi() serves (/healthz, /metrics, /api/...).
bool isApiPath(std::string_view target);
// True for the API paths that need the token when one is set: all but /healthz, which
// health checks (Docker, load balancers) call without one.
bool needsToken(std::string_view target);

// The answer for a GET/HEAD of an API path, or nullopt when `target` is not an API path
// (static files). `admin` (may be null) adds the store's closed sessions to listings.
// `if_none_match`: the request's If-None-Match (a tile whose ETag matches answers 304).
std::optional<HttpAnswer> answerApi(const MapServer& server, const SessionAdmin* admin,
                                    std::string_view method, std::string_view target,
                                    std::string_view if_none_match = {});

// True for the requests answerAdmin() serves: POST /api/sessions/{id}/open|close,
// DELETE /api/sessions/{id}, POST /api/sessions/merge (its "align": "auto" finds the
// transform), POST /api/sessions/align (200 with the transform, 422 with the reason it was
// refused). They may take seconds (a replay, an alignment), so the network layer runs them
// off its own thread.
bool isAdminRequest(std::string_view method, std::string_view target);
HttpAnswer answerAdmin(SessionAdmin* admin, const MapServer& server, std::string_view method,
                       std::string_view target, const std::string& body);

// Every session as a JSON array (GET /api/sessions, the viewer's "sessions" message): the
// loaded ones, then (with `admin`) the store's closed ones.
std::string sessionListJson(const MapServer& server, const SessionAdmin* admin);

}  // namespace stereomap::core
