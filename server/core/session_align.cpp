#include "server/core/session_align.hpp"

#include <algorithm>
#include <cstdio>
#include <set>
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

nlohmann::json transformJson(const common::Rigid3& T) {
  common::Quat q = T.rotation.normalized();
  if (q.w() < 0) q.coeffs() = -q.coeffs();
  const common::Vec3& t = T.translation;
  return {t.x(), t.y(), t.z(), q.x(), q.y(), q.z(), q.w()};
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
  out["transform"] = transformJson(alignment.T_a_b);
  out["overlap"] = alignment.overlap;
  out["agreement"] = alignment.agreement;
  out["rmse_m"] = alignment.rmse_m;
  out["confidence"] = alignment.confidence;
  return out;
}

size_t SitePlan::registered() const {
  return static_cast<size_t>(std::count_if(members.begin(), members.end(),
                                           [](const SiteMember& m) { return m.registered; }));
}

nlohmann::json SitePlan::json() const {
  nlohmann::json sessions = nlohmann::json::array(), left_out = nlohmann::json::array();
  for (const auto& m : members) {
    if (!m.registered) {
      left_out.push_back({{"session", m.id}, {"reason", m.reason}});
      continue;
    }
    nlohmann::json entry = {{"session", m.id}, {"transform", transformJson(m.T_site_session)}};
    if (!m.onto.empty()) {
      entry["onto"] = m.onto;
      entry["overlap"] = m.alignment.overlap;
      entry["rmse_m"] = m.alignment.rmse_m;
    }
    sessions.push_back(std::move(entry));
  }
  return {{"sessions", std::move(sessions)}, {"left_out", std::move(left_out)}};
}

MergeRequest SitePlan::mergeRequest(const std::string& into) const {
  MergeRequest request;
  for (const auto& m : members) {
    if (m.registered) request.sources.push_back({m.id, m.T_site_session});
  }
  request.into = into;
  request.origin = nlohmann::json{{"site", json()}}.dump();
  return request;
}

std::string siteMemberLine(const std::string& site, const SiteMember& member) {
  const std::string head = "site " + site + ": " + member.id + ": ";
  if (!member.registered) return head + "left out (" + member.reason + ")";
  if (member.onto.empty()) return head + "the site's frame";
  const auto t = transformJson(member.T_site_session);
  char text[256];
  std::snprintf(text, sizeof(text),
                "t %.4f %.4f %.4f q %.6f %.6f %.6f %.6f, onto %s (overlap %.0f%%, rmse %.4f m)",
                t[0].get<double>(), t[1].get<double>(), t[2].get<double>(), t[3].get<double>(),
                t[4].get<double>(), t[5].get<double>(), t[6].get<double>(), member.onto.c_str(),
                100 * member.alignment.overlap, member.alignment.rmse_m);
  return head + text;
}

common::Result<SitePlan> planSite(const SessionMapSource& map_of,
                                  const std::vector<std::string>& sessions,
                                  const align::AlignOptions& options,
                                  const std::function<void(const SiteMember&)>& joined) {
  MergeRequest names;
  for (const auto& id : sessions) names.sources.push_back({id, common::Rigid3::identity()});
  names.into = sessions.empty() ? "" : sessions.front();  // checked by name only below
  if (auto problem = names.problem(); !problem.empty()) {
    return common::makeError(common::ErrorCode::kInvalidArgument, "site: " + problem);
  }
  std::vector<std::unique_ptr<fusion::OccupancyMap>> maps;
  for (const auto& id : sessions) {
    auto map = map_of(id);
    if (!map) return map.error();
    maps.push_back(std::move(map).value());
  }
  SitePlan plan;
  for (const auto& id : sessions) plan.members.push_back({.id = id});
  plan.members.front().registered = true;
  if (joined) joined(plan.members.front());
  std::vector<size_t> order = {0};  // registered members, in the order they joined
  std::set<std::pair<size_t, size_t>> tried;
  for (bool progress = true; progress;) {
    progress = false;
    for (size_t i = 1; i < plan.members.size(); ++i) {
      SiteMember& member = plan.members[i];
      for (size_t k = 0; k < order.size() && !member.registered; ++k) {
        const size_t j = order[k];
        if (!tried.insert({i, j}).second) continue;
        auto aligned = align::alignMaps(*maps[j], *maps[i], options);
        if (!aligned) {
          member.reason = "onto " + sessions[j] + ": " + aligned.error().message;
          continue;
        }
        member.alignment = *aligned;
        if (!aligned->found) {
          member.reason = "onto " + sessions[j] + ": " + aligned->reason;
          continue;
        }
        member.registered = true;
        member.onto = sessions[j];
        member.T_site_session = plan.members[j].T_site_session * aligned->T_a_b;
        member.reason.clear();
        order.push_back(i);
        progress = true;
        if (joined) joined(member);
      }
    }
  }
  for (auto& member : plan.members) {
    if (member.registered) continue;
    member.reason = "aligns onto none of the site's sessions (last: " + member.reason + ")";
    if (joined) joined(member);
  }
  return plan;
}

}  // namespace stereomap::core
