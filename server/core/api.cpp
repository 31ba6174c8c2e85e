#include "server/core/api.hpp"

#include <nlohmann/json.hpp>

#include <algorithm>
#include <map>
#include <optional>

#include "common/transform_args.hpp"
#include "common/url.hpp"
#include "server/core/session_align.hpp"
#include "server/core/session_json.hpp"
#include "server/core/validate.hpp"

namespace stereomap::core {

std::string errorBody(const std::string& message) {
  return nlohmann::json{{"error", message}}.dump(-1, ' ', false,
                                                 nlohmann::json::error_handler_t::replace) +
         "\n";
}

namespace {

using nlohmann::json;

HttpAnswer error(int status, const std::string& message) {
  return {status, "application/json", errorBody(message), ""};
}

// Ids come from URLs and bodies and name directories: checked before anything else sees them.
std::optional<HttpAnswer> badId(const std::string& what, const std::string& id) {
  if (isValidId(id)) return std::nullopt;
  const std::string shown =
      id.size() > 80 ? id.substr(0, 80) + "... (" + std::to_string(id.size()) + " bytes)" : id;
  return error(400, what + " '" + shown + "' is not 1-" + std::to_string(proto::kMaxIdLength) +
                        " of [A-Za-z0-9._-] (and not . or ..)");
}

// GET /api/sessions/{id}/landing: each vehicle's newest view of the landing pad.
json landingJson(const std::string& id, const std::vector<proto::LandingTargetMsg>& targets) {
  static const char* kStates[] = {"SEARCHING", "TRACKING", "LOST"};
  json vehicles = json::array();
  for (const auto& t : targets) {
    json entry = {{"vehicle_id", t.vehicle_id},
                  {"stamp_ns", t.stamp_ns},
                  {"seq", t.seq},
                  {"state", kStates[static_cast<int>(t.state)]},
                  {"mode", t.mode == proto::LandingMode::kPatent ? "patent" : "default"},
                  {"reason", t.reason},
                  {"has_pose", t.has_pose}};
    if (t.has_pose) {
      entry["pad_in_camera"] = {{"position", t.camera_position},
                                {"orientation", t.camera_orientation},
                                {"covariance", t.camera_covariance}};
      entry["pad_in_map"] = {{"position", t.map_position},
                             {"orientation", t.map_orientation},
                             {"covariance", t.map_covariance}};
      entry["deck"] = {{"velocity", t.deck_velocity},
                       {"heave_rate", t.deck_velocity[2]},
                       {"angular_rate", t.deck_angular_rate}};
      entry["distance_m"] = t.distance;
      entry["bearing_deg"] = t.bearing_deg;
      entry["reprojection_px"] = t.reprojection_px;
    }
    vehicles.push_back(std::move(entry));
  }
  return {{"session", id}, {"vehicles", std::move(vehicles)}};
}

// Splits "/api/sessions/x/y?q" into path segments (query dropped).
std::vector<std::string> segments(std::string_view target) {
  target = target.substr(0, target.find('?'));
  std::vector<std::string> parts;
  size_t start = 1;
  while (start <= target.size()) {
    const size_t end = std::min(target.find('/', start), target.size());
    if (end > start) parts.emplace_back(target.substr(start, end - start));
    start = end + 1;
  }
  return parts;
}

std::string queryValue(std::string_view target, std::string_view key) {
  return common::queryParameter(target, key).value_or("");
}

// A tile version's tag, "<map epoch, hex>-<version>": the ETag's text and the `v` of a
// versioned tile URL. The version alone would repeat after a restart or on another server
// (versions start again): the map's epoch makes it unique.
std::string tileTag(uint64_t epoch, uint64_t version) {
  char tag[48];
  std::snprintf(tag, sizeof(tag), "%llx-%llu", static_cast<unsigned long long>(epoch),
                static_cast<unsigned long long>(version));
  return tag;
}

// GET /api/sessions/{id}/tiles and /api/sessions/{id}/tiles/{level}/{key}[?v=TAG] (FORMAT.md).
HttpAnswer answerTiles(const Session& session, const std::vector<std::string>& parts,
                       std::string_view target, std::string_view if_none_match) {
  using proto::tiles::kLevels;
  const auto& tiles = session.tiles();
  if (parts.size() == 4) {
    json list = json::array();
    for (const auto& info : tiles.list()) {
      const auto tile = tiles.find(info.key);
      for (unsigned level = 0; level < kLevels; ++level) {
        if (info.cells[level] == 0) continue;
        // The bytes as served (encoded once per tile version, then kept).
        const size_t bytes =
            tile && tile->version() == info.version ? tile->encoded(level)->size() : 0;
        list.push_back(
            {{"level", level},
             {"key", info.key.text()},
             {"version", info.version},
             {"voxels", info.cells[level]},
             {"bytes", bytes},
             {"url", "/api/sessions/" + session.id() + "/tiles/" + std::to_string(level) + "/" +
                         info.key.text() + "?v=" + tileTag(tiles.epoch(), info.version)}});
      }
    }
    const json index = {{"session", session.id()},
                        {"levels", kLevels},
                        {"tile_voxels", 1 << proto::tiles::kTileBits},
                        {"resolution", tiles.resolution()},
                        {"version", tiles.summary().version},
                        {"tiles", std::move(list)}};
    return HttpAnswer{200, "application/json", index.dump() + "\n", "", ""};
  }
  if (parts.size() != 6) return error(404, "a tile is /api/sessions/{id}/tiles/{level}/{key}");
  const std::string& level_text = parts[4];
  if (level_text.size() != 1 || level_text[0] < '0' || level_text[0] >= '0' + int{kLevels}) {
    return error(400, "tile level must be 0.." + std::to_string(kLevels - 1));
  }
  const unsigned level = static_cast<unsigned>(level_text[0] - '0');
  const auto key = proto::tiles::TileKey::parse(parts[5]);
  if (!key) return error(400, "a tile key is x_y_z (integers), e.g. 3_-2_0");
  const auto tile = tiles.find(*key);
  if (!tile) return error(404, "no occupied tile " + key->text() + " in this map");
  const std::string tag = tileTag(tiles.epoch(), tile->version());
  const std::string etag = "\"" + tag + "\"";
  // A versioned URL (the index's `url`) names one version for good: a proxy may keep it
  // forever. Any other version is not served under it.
  const auto wanted = common::queryParameter(target, "v");
  if (wanted && *wanted != tag) {
    return error(404, "tile " + key->text() + " is no longer at version " + *wanted + " (now " +
                          tag + "): read the index again");
  }
  if (if_none_match == "*" || if_none_match.find(etag) != std::string_view::npos) {
    return HttpAnswer{304, "", "", "", etag, wanted.has_value()};
  }
  return HttpAnswer{200,  "application/octet-stream", *tile->encoded(level), "",
                    etag, wanted.has_value()};
}

// GET /api/cluster/route?session=ID: where the cluster's proxy sends a request for the
// session (header X-Stereomap-Upstream, host:port): its owner, or this server when no live
// server owns it (or the id is bad), which then answers as for any unknown session.
HttpAnswer answerRoute(const SessionAdmin* admin, const std::string& session) {
  const auto self = admin != nullptr ? admin->selfAddress() : std::nullopt;
  if (!self) return error(404, "this server is not in a cluster (stereomap-server --cluster)");
  std::optional<std::string> owner;
  if (isValidId(session)) owner = admin->routeTo(session);
  const std::string upstream = owner.value_or(*self);
  HttpAnswer answer{
      200, "application/json",
      json{{"session", session}, {"upstream", upstream}, {"owned", owner.has_value()}}.dump() +
          "\n",
      ""};
  answer.headers.emplace_back("X-Stereomap-Upstream", upstream);
  return answer;
}

}  // namespace

std::string sessionListJson(const MapServer& server, const SessionAdmin* admin) {
  json list = json::array();
  for (const auto& session : server.sessions()) list.push_back(sessionObject(session->status()));
  if (admin != nullptr) {
    for (const auto& closed : admin->closedSessions()) list.push_back(sessionObject(closed));
    for (const auto& remote : admin->remoteSessions()) {
      if (!server.find(remote.id)) list.push_back(sessionObject(remote));
    }
  }
  return list.dump();
}

bool isApiPath(std::string_view target) {
  const auto parts = segments(target);
  if (parts.empty()) return false;
  return parts[0] == "api" ||
         (parts.size() == 1 && (parts[0] == "healthz" || parts[0] == "metrics"));
}

bool needsToken(std::string_view target) {
  if (!isApiPath(target)) return false;
  const auto parts = segments(target);
  return !(parts.size() == 1 && parts[0] == "healthz");
}

std::optional<HttpAnswer> answerApi(const MapServer& server, const SessionAdmin* admin,
                                    std::string_view method, std::string_view target,
                                    std::string_view if_none_match) {
  if (!isApiPath(target)) return std::nullopt;
  const auto parts = segments(target);
  if (method != "GET" && method != "HEAD") {
    return error(405,
                 "use GET here (POST .../open, .../close, /api/sessions/merge, "
                 "/api/sessions/align and /api/sessions/site, DELETE /api/sessions/{id} manage "
                 "sessions)");
  }

  if (parts[0] == "healthz") {
    // 503 while degraded, so that health checks (Docker, load balancers) notice.
    const auto health = server.storeHealth();
    if (health.ok) return HttpAnswer{200, "text/plain", "ok\n", ""};
    return HttpAnswer{503, "text/plain",
                      "degraded: " + health.reason +
                          "; serving stored maps read-only, new samples are refused until the "
                          "store can be written again\n",
                      ""};
  }
  if (parts[0] == "metrics") {
    return HttpAnswer{200, "text/plain; version=0.0.4", server.metricsText(), ""};
  }
  if (parts.size() == 3 && parts[1] == "cluster" && parts[2] == "route") {
    return answerRoute(admin, queryValue(target, "session"));
  }
  if (parts.size() < 2 || parts[1] != "sessions") {
    return error(404, "unknown API path '" + std::string(target) + "'");
  }
  if (parts.size() == 2)
    return HttpAnswer{200, "application/json", sessionListJson(server, admin) + "\n", ""};
  if (auto bad = badId("session id", parts[2])) return bad;
  const std::string vehicle = queryValue(target, "vehicle");
  if (!vehicle.empty()) {
    if (auto bad = badId("vehicle id", vehicle)) return bad;
  }
  const auto session = server.find(parts[2]);
  if (!session && admin != nullptr) {
    for (const auto& closed : admin->closedSessions()) {
      if (closed.id != parts[2]) continue;
      if (parts.size() == 3) {
        return HttpAnswer{200, "application/json", sessionObject(closed).dump() + "\n", ""};
      }
      return error(409, "session '" + parts[2] + "' is " +
                            (closed.closed ? "closed" : "ended and out of memory") +
                            ": open it first (POST /api/sessions/" + parts[2] + "/open)");
    }
  }
  if (!session) return error(404, "no session '" + parts[2] + "'");
  if (parts.size() == 3) {
    return HttpAnswer{200, "application/json", sessionObject(session->status()).dump() + "\n", ""};
  }
  if (parts[3] == "tiles") return answerTiles(*session, parts, target, if_none_match);
  if (parts.size() == 4 && parts[3] == "landing") {
    return HttpAnswer{200, "application/json",
                      landingJson(parts[2], session->landingTargets()).dump() + "\n", ""};
  }
  // Resource -> export format; the height band and scale come from the query.
  static const std::map<std::string, std::string, std::less<>> kFormats = {
      {"trajectory.tum", "tum"}, {"map.ot", "ot"},     {"map.ply", "ply"},    {"map.png", "png"},
      {"map.bt", "bt"},          {"map2d.pgm", "pgm"}, {"map2d.yaml", "yaml"}};
  const auto format = parts.size() == 4 ? kFormats.find(parts[3]) : kFormats.end();
  if (format != kFormats.end()) {
    ExportRequest request{format->second};
    request.vehicle = vehicle;
    if (request.format == "png" || request.format == "pgm" || request.format == "yaml") {
      // Height band in metres: ?zmin=0.5&zmax=2.0 (default: all heights).
      try {
        if (auto v = queryValue(target, "zmin"); !v.empty()) request.z_min = std::stod(v);
        if (auto v = queryValue(target, "zmax"); !v.empty()) request.z_max = std::stod(v);
        if (auto v = queryValue(target, "scale"); !v.empty()) request.scale = std::stoi(v);
      } catch (const std::exception&) {
        return error(400, "zmin and zmax must be numbers (metres), scale a whole number");
      }
      if (!(request.z_min <= request.z_max)) return error(400, "zmin must not exceed zmax");
      if (request.scale < 1 || request.scale > 16)
        return error(400, "scale must be 1..16 pixels per voxel");
    }
    auto file = exportSession(*session, parts[2], request);
    if (!file) {
      const auto code = file.error().code;
      return error(code == common::ErrorCode::kTooLarge          ? 413
                   : code == common::ErrorCode::kIo              ? 500
                   : code == common::ErrorCode::kInvalidArgument ? 400
                                                                 : 404,
                   file.error().message);
    }
    return HttpAnswer{200, file->content_type, std::move(file->content), file->name};
  }
  return error(404, "unknown session resource '" + std::string(target) + "'");
}

bool isAdminRequest(std::string_view method, std::string_view target) {
  if (method != "POST" && method != "DELETE") return false;
  const auto parts = segments(target);
  return parts.size() >= 3 && parts[0] == "api" && parts[1] == "sessions";
}

namespace {

HttpAnswer errorOf(const common::Error& failure) {
  const auto code = failure.code;
  return error(code == common::ErrorCode::kNotFound          ? 404
               : code == common::ErrorCode::kConflict        ? 409
               : code == common::ErrorCode::kInvalidArgument ? 400
               : code == common::ErrorCode::kUnavailable     ? 503
                                                             : 500,
               failure.message);
}

// On the server: one OpenMP thread, so that ingest keeps the other core.
align::AlignOptions serverAlignOptions() { return {.threads = 1}; }

common::Result<align::Alignment> alignOnServer(const MapServer& server, SessionAdmin* admin,
                                               const std::string& first,
                                               const std::string& second) {
  return alignSessions([&](const std::string& id) { return sessionMap(server, admin, id); }, first,
                       second, serverAlignOptions());
}

// 200 with the alignment, or 422 with the reason it was refused.
HttpAnswer answerAlign(const MapServer& server, SessionAdmin* admin, const std::string& first,
                       const std::string& second) {
  auto found = alignOnServer(server, admin, first, second);
  if (!found) return errorOf(found.error());
  return HttpAnswer{found->found ? 200 : 422, "application/json",
                    alignmentJson(first, second, *found).dump() + "\n", ""};
}

}  // namespace

HttpAnswer answerAdmin(SessionAdmin* admin, const MapServer& server, std::string_view method,
                       std::string_view target, const std::string& body) {
  if (admin == nullptr) return error(503, "this server keeps no store: sessions cannot be managed");
  const auto parts = segments(target);
  common::Status done = common::Ok{};
  std::string id;
  if (method == "POST" && parts.size() == 3 && parts[2] == "align") {
    std::string first, second;
    try {
      const json doc = json::parse(body);
      first = doc.at("first").get<std::string>();
      second = doc.at("second").get<std::string>();
    } catch (const std::exception&) {
      return error(400, "align wants a JSON body {\"first\": ID, \"second\": ID}");
    }
    for (const auto& [what, value] : {std::pair{"first", first}, std::pair{"second", second}}) {
      if (auto bad = badId(std::string("align: ") + what, value)) return *bad;
    }
    return answerAlign(server, admin, first, second);
  }
  std::optional<json> alignment;  // a merge's, with "align": "auto"
  if (method == "POST" && parts.size() == 3 && parts[2] == "site") {
    std::vector<std::string> sessions;
    try {
      const json doc = json::parse(body);
      id = doc.at("into").get<std::string>();
      sessions = doc.at("sessions").get<std::vector<std::string>>();
    } catch (const std::exception&) {
      return error(400,
                   "site wants a JSON body {\"into\": NEW_ID, \"sessions\": [ID, ID, ...]} (two "
                   "or more sessions; the first gives the site's frame)");
    }
    if (auto bad = badId("site: into", id)) return *bad;
    for (const auto& session : sessions) {
      if (auto bad = badId("site: sessions", session)) return *bad;
    }
    if (server.find(id)) return error(409, "session '" + id + "' already exists");
    auto plan = planSite([&](const std::string& s) { return sessionMap(server, admin, s); },
                         sessions, serverAlignOptions());
    if (!plan) return errorOf(plan.error());
    if (plan->registered() < 2) {
      const json refused = {
          {"site", plan->json()},
          {"reason", "no session aligns onto " + sessions.front() + ": nothing made"}};
      return HttpAnswer{422, "application/json", refused.dump() + "\n", ""};
    }
    done = admin->merge(plan->mergeRequest(id));
  } else if (method == "POST" && parts.size() == 3 && parts[2] == "merge") {
    MergeRequest request;
    bool align_auto = false;
    try {
      const json doc = json::parse(body);
      request = MergeRequest::pair(doc.at("first").get<std::string>(),
                                   doc.at("second").get<std::string>(),
                                   doc.at("into").get<std::string>());
      if (doc.contains("transform")) {
        const auto T = common::rigidFromTxyzQxyzw(doc["transform"].get<std::vector<double>>());
        if (!T) throw std::invalid_argument("transform");
        request.sources[1].T_into_source = *T;
      }
      if (doc.contains("align")) {
        if (doc["align"] != "auto" || doc.contains("transform")) {
          throw std::invalid_argument("align");
        }
        align_auto = true;
      }
    } catch (const std::exception&) {
      return error(400,
                   "merge wants a JSON body {\"first\": ID, \"second\": ID, \"into\": NEW_ID, "
                   "\"transform\": [tx, ty, tz, qx, qy, qz, qw] (optional, a unit quaternion; "
                   "maps the second session's frame into the first's) or \"align\": \"auto\" "
                   "(found from the maps)}");
    }
    for (const auto& [what, value] :
         {std::pair{"first", request.sources[0].id}, std::pair{"second", request.sources[1].id},
          std::pair{"into", request.into}}) {
      if (auto bad = badId(std::string("merge: ") + what, value)) return *bad;
    }
    id = request.into;
    if (align_auto) {
      if (server.find(request.into)) {
        return error(409, "session '" + request.into + "' already exists");
      }
      const std::string &first = request.sources[0].id, &second = request.sources[1].id;
      auto found = alignOnServer(server, admin, first, second);
      if (!found) return errorOf(found.error());
      alignment = alignmentJson(first, second, *found);
      if (!found->found) return HttpAnswer{422, "application/json", alignment->dump() + "\n", ""};
      request.sources[1].T_into_source = found->T_a_b;
    }
    done = admin->merge(request);
  } else if (auto bad = badId("session id", parts[2])) {
    return *bad;
  } else if (method == "POST" && parts.size() == 4 && parts[3] == "open") {
    id = parts[2];
    done = admin->open(id);
  } else if (method == "POST" && parts.size() == 4 && parts[3] == "close") {
    id = parts[2];
    done = admin->close(id);
  } else if (method == "DELETE" && parts.size() == 3) {
    done = admin->remove(parts[2]);
    if (done)
      return HttpAnswer{200, "application/json", json{{"deleted", parts[2]}}.dump() + "\n", ""};
  } else {
    return error(404, "unknown request " + std::string(method) + " " + std::string(target));
  }
  if (!done) return errorOf(done.error());
  if (const auto session = server.find(id)) {
    auto object = sessionObject(session->status());
    if (alignment) object["alignment"] = *alignment;
    return HttpAnswer{200, "application/json", object.dump() + "\n", ""};
  }
  for (const auto& closed : admin->closedSessions()) {
    if (closed.id == id)
      return HttpAnswer{200, "application/json", sessionObject(closed).dump() + "\n", ""};
  }
  return HttpAnswer{200, "application/json", json{{"id", id}}.dump() + "\n", ""};
}

}  // namespace stereomap::core
