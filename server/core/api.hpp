// The server's HTTP API as plain functions of the MapServer (no networking here): REST
// answers for /healthz, /metrics and /api/sessions..., so the Beast layer only transports.
// See docs/PROTOCOL.md.
#pragma once

#include <optional>
#include <string>
#include <string_view>

#include "server/core/map_server.hpp"

namespace stereomap::core {

struct HttpAnswer {
  int status = 200;
  std::string content_type = "application/json";
  std::string body;
  std::string filename;  // when set: offered as a download with this name
};

// True for the paths answerApi() serves (/healthz, /metrics, /api/...).
bool isApiPath(std::string_view target);

// The answer for an API path, or nullopt when `target` is not an API path (static files).
std::optional<HttpAnswer> answerApi(const MapServer& server, std::string_view method,
                                    std::string_view target);

// The JSON object describing a session (GET /api/sessions and, with message_type
// "session", the viewer's message).
std::string sessionJson(const SessionStatus& status, const char* message_type = nullptr);

}  // namespace stereomap::core
