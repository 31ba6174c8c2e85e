#include "server/core/session_json.hpp"

#include <array>

namespace stereomap::core {

using nlohmann::json;

namespace {

json textOrNull(const std::string& text) { return text.empty() ? json(nullptr) : json(text); }

}  // namespace

json boundsJson(const common::Box3& bounds) {
  if (bounds.empty()) return nullptr;
  return {{"min", {bounds.min.x(), bounds.min.y(), bounds.min.z()}},
          {"max", {bounds.max.x(), bounds.max.y(), bounds.max.z()}}};
}

json sessionObject(const SessionStatus& s, SessionFields fields) {
  json object = {{"id", s.id},
                 {"vehicle", s.vehicles.empty() ? "" : s.vehicles.front()},
                 {"vehicles", s.vehicles},
                 {"state", stateName(s)},
                 {"resolution", s.resolution},
                 {"frames", s.frames_fused},
                 {"occupied_voxels", s.occupied_voxels},
                 {"bounds", boundsJson(s.bounds)}};
  if (fields == SessionFields::kCatalog) return object;
  object.update(json{{"frames_received", s.frames_received},
                     {"dropped_frames", s.frames_dropped},
                     {"deferred_frames", s.frames_deferred},
                     {"fusion_backlog", s.backlog},
                     {"poses", s.poses},
                     {"bytes_received", s.bytes_received},
                     {"ended_by", textOrNull(s.ended_by)},
                     {"store_error", textOrNull(s.store_error)},
                     {"samples_refused", s.samples_refused},
                     {"corrections", s.corrections},
                     {"refusions", s.refusions},
                     {"refusing", s.refusing},
                     {"refusion_error", textOrNull(s.refusion_error)},
                     {"publish_lag_ms",
                      {{"p50", 1000 * s.publish_lag.quantile(0.5)},
                       {"p95", 1000 * s.publish_lag.quantile(0.95)}}}});
  if (!s.server.empty()) object["server"] = s.server;
  if (!s.origin.empty()) {
    if (auto origin = json::parse(s.origin, nullptr, false); origin.is_object()) {
      object["origin"] = std::move(origin);
    }
  }
  json counters = json::array();
  for (const auto& [v, received_ns] : s.vehicle_status) {
    counters.push_back({{"vehicle_id", v.vehicle_id},
                        {"frames", v.frames},
                        {"skipped_frames", v.skipped_frames},
                        {"late_frames", v.late_frames},
                        {"spool_samples", v.spool_samples},
                        {"spool_bytes", v.spool_bytes},
                        {"given_up", v.given_up},
                        {"held_back", v.held_back},
                        {"session_closed", v.session_closed},
                        {"received_s", static_cast<double>(received_ns) * 1e-9}});
  }
  object["vehicle_status"] = std::move(counters);
  json frames = json::array();
  for (const auto& f : s.vehicle_frames) {
    json entry{{"vehicle_id", f.vehicle_id},
               {"frame", f.aligned ? "aligned" : "aligning"},
               {"attempts", f.attempts},
               {"reason", textOrNull(f.reason)},
               {"held_frames", f.held_frames}};
    if (f.aligned) {
      common::Quat q = f.T_session_own.rotation.normalized();
      if (q.w() < 0) q.coeffs() = -q.coeffs();
      const common::Vec3& t = f.T_session_own.translation;
      entry.update(json{{"transform", {t.x(), t.y(), t.z(), q.x(), q.y(), q.z(), q.w()}},
                        {"overlap", f.overlap},
                        {"rmse_m", f.rmse_m},
                        {"aligned_s", f.aligned_s}});
    }
    frames.push_back(std::move(entry));
  }
  object["vehicle_frames"] = std::move(frames);
  return object;
}

std::string sessionJson(const SessionStatus& status, const char* message_type) {
  json object = sessionObject(status);
  if (message_type != nullptr) object["type"] = message_type;
  return object.dump();
}

SessionStatus sessionFromJson(const std::string& id, const json& doc) {
  SessionStatus s;
  s.id = id;
  s.ended = true;
  if (!doc.is_object()) return s;
  auto count = [&](const char* key, uint64_t fallback = 0) {
    const auto found = doc.find(key);
    return found != doc.end() && found->is_number_unsigned() ? found->get<uint64_t>() : fallback;
  };
  auto text = [&](const char* key) {
    const auto found = doc.find(key);
    return found != doc.end() && found->is_string() ? found->get<std::string>() : std::string();
  };
  if (const auto vehicles = doc.find("vehicles"); vehicles != doc.end() && vehicles->is_array()) {
    for (const auto& v : *vehicles) {
      if (v.is_string()) s.vehicles.push_back(v.get<std::string>());
    }
  }
  if (const auto r = doc.find("resolution"); r != doc.end() && r->is_number()) {
    s.resolution = r->get<double>();
  }
  s.frames_fused = count("frames");
  s.frames_received = count("frames_received", s.frames_fused);
  s.frames_dropped = count("dropped_frames");
  s.occupied_voxels = count("occupied_voxels");
  s.poses = count("poses");
  s.bytes_received = count("bytes_received");
  s.samples_refused = count("samples_refused");
  s.corrections = count("corrections");
  s.refusions = count("refusions");
  s.ended_by = text("ended_by");
  if (const auto origin = doc.find("origin"); origin != doc.end() && origin->is_object()) {
    s.origin = origin->dump();
  }
  const std::string state = text("state");
  s.closed = state == "closed";
  s.read_only = state == "opened";
  s.ended = state != "live";  // no state: a stored session that stopped unsaved
  const auto bounds = doc.find("bounds");
  if (bounds != doc.end() && bounds->is_object() && bounds->contains("min") &&
      bounds->contains("max")) {
    try {
      const auto lo = (*bounds)["min"].get<std::array<double, 3>>();
      const auto hi = (*bounds)["max"].get<std::array<double, 3>>();
      s.bounds.extend({lo[0], lo[1], lo[2]});
      s.bounds.extend({hi[0], hi[1], hi[2]});
    } catch (const json::exception&) {
      // Not three numbers each: no bounds.
    }
  }
  return s;
}

}  // namespace stereomap::core
