#include "server/core/session_align.hpp"

#include <sstream>

namespace stereomap::core {

common::Result<std::unique_ptr<fusion::OccupancyMap>> sessionMap(const MapServer& server,
                                                                 SessionAdmin* admin,
                                                                 const std::string& id) {
  auto session = server.find(id);
  if (!session && admin != nullptr) {
    if (auto opened = admin->open(id); !opened) return opened.error();
    session = server.find(id);
  }
  if (!session) {
    return common::makeError(common::ErrorCode::kNotFound, "no session '" + id + "'");
  }
  session->waitUntilFused();
  auto bytes = session->mapFull();
  if (!bytes) return bytes.error();
  std::istringstream in(*bytes);
  return fusion::OccupancyMap::load(in);
}

common::Result<align::Alignment> alignSessions(const SessionMapSource& map_of,
                                               const std::string& first, const std::string& second,
                                               const align::AlignOptions& options) {
  if (first == second) {
    return common::makeError(common::ErrorCode::kInvalidArgument,
                             "align needs two different sessions");
  }
  auto a = map_of(first);
  if (!a) return a.error();
  auto b = map_of(second);
  if (!b) return b.error();
  auto aligned = align::alignMaps(**a, **b, options);
  if (!aligned) {
    return common::makeError(aligned.error().code,
                             first + " and " + second + ": " + aligned.error().message);
  }
  return aligned;
}

nlohmann::json alignmentJson(const std::string& first, const std::string& second,
                             const align::Alignment& alignment) {
  nlohmann::json out{{"first", first},
                     {"second", second},
                     {"found", alignment.found},
                     {"line", align::alignLine(first, second, alignment)},
                     {"voxels", {alignment.voxels_a, alignment.voxels_b}},
                     {"seconds", alignment.seconds}};
  if (!alignment.found) {
    out["reason"] = alignment.reason;
    return out;
  }
  common::Quat q = alignment.T_a_b.rotation.normalized();
  if (q.w() < 0) q.coeffs() = -q.coeffs();
  const common::Vec3& t = alignment.T_a_b.translation;
  out["transform"] = {t.x(), t.y(), t.z(), q.x(), q.y(), q.z(), q.w()};
  out["overlap"] = alignment.overlap;
  out["agreement"] = alignment.agreement;
  out["rmse_m"] = alignment.rmse_m;
  out["confidence"] = alignment.confidence;
  return out;
}

}  // namespace stereomap::core
