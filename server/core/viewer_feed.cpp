#include "server/core/viewer_feed.hpp"

#include <nlohmann/json.hpp>

#include <algorithm>
#include <iterator>

#include "common/time.hpp"
#include "server/core/api.hpp"

namespace stereomap::core {

namespace {

using fusion::VoxelIndex;
using nlohmann::json;

json flatten(const std::vector<VoxelIndex>& voxels) {
  std::vector<int32_t> flat;
  flat.reserve(voxels.size() * 3);
  for (const auto& v : voxels) {
    flat.push_back(v.x);
    flat.push_back(v.y);
    flat.push_back(v.z);
  }
  return flat;
}

std::string voxelsMessage(const std::string& session, double resolution, uint64_t version,
                          bool reset, const std::vector<VoxelIndex>& add,
                          const std::vector<VoxelIndex>& remove) {
  return json{{"type", "voxels"},         {"session", session}, {"resolution", resolution},
              {"version", version},       {"reset", reset},     {"add", flatten(add)},
              {"remove", flatten(remove)}}
      .dump();
}

// One "poses" message per vehicle, poses in arrival order.
void appendPoseMessages(const std::string& session, const std::vector<PoseRecord>& poses,
                        bool reset, std::vector<std::string>& out) {
  std::map<std::string, json> by_vehicle;
  std::vector<std::string> order;
  for (const auto& pose : poses) {
    auto [it, inserted] = by_vehicle.try_emplace(pose.vehicle_id, json::array());
    if (inserted) order.push_back(pose.vehicle_id);
    const auto& t = pose.T_map_body.translation;
    const auto& q = pose.T_map_body.rotation;
    it->second.push_back(
        {common::nsToSeconds(pose.stamp_ns), t.x(), t.y(), t.z(), q.x(), q.y(), q.z(), q.w()});
  }
  for (const auto& vehicle : order) {
    out.push_back(json{{"type", "poses"},
                       {"session", session},
                       {"vehicle", vehicle},
                       {"reset", reset},
                       {"poses", std::move(by_vehicle[vehicle])}}
                      .dump());
  }
}

}  // namespace

ViewerFeed::ViewerFeed(const MapServer& server) : server_(server) {}

std::vector<std::string> ViewerFeed::welcome() const {
  std::vector<std::string> out;
  out.push_back(json{{"type", "hello"}, {"protocol", 1}, {"server", "stereomap 0.1.0"}}.dump());
  for (const auto& id : order_) {
    const auto& state = sessions_.at(id);
    out.push_back(state.status_json);
    std::vector<VoxelIndex> voxels;
    for (const auto& [key, tile] : state.tiles) {
      const auto in_tile = tile->voxels();
      voxels.insert(voxels.end(), in_tile.begin(), in_tile.end());
    }
    out.push_back(voxelsMessage(id, state.resolution, state.version, true, voxels, {}));
    const auto session = server_.find(id);
    auto poses = session ? session->trajectory(0) : std::vector<PoseRecord>{};
    poses.resize(std::min(poses.size(), state.poses_sent));
    appendPoseMessages(id, poses, true, out);
  }
  return out;
}

std::vector<std::string> ViewerFeed::poll() {
  std::vector<std::string> out;
  const auto sessions = server_.sessions();
  // Sessions the server no longer holds (closed into the store, or deleted).
  for (auto id = order_.begin(); id != order_.end();) {
    const bool held = std::any_of(sessions.begin(), sessions.end(),
                                  [&](const auto& session) { return session->id() == *id; });
    if (held) {
      ++id;
      continue;
    }
    out.push_back(json{{"type", "session_removed"}, {"id", *id}}.dump());
    sessions_.erase(*id);
    id = order_.erase(id);
  }
  for (const auto& session : sessions) {
    auto [it, inserted] = sessions_.try_emplace(session->id());
    SessionState& state = it->second;
    if (inserted) order_.push_back(session->id());
    // The tiles changed since the last poll, as voxels added and removed.
    const auto& tiles = session->tiles();
    state.resolution = tiles.resolution();
    auto changed = tiles.changedSince(state.version);
    if (!changed) {  // too far behind: compare every tile
      changed.emplace();
      for (const auto& info : tiles.list()) changed->emplace_back(info.key, info.version);
      for (const auto& [key, tile] : state.tiles) changed->emplace_back(key, 0);
    }
    std::vector<VoxelIndex> add, remove;
    for (const auto& [key, version] : *changed) {
      state.version = std::max(state.version, version);
      auto tile = tiles.find(key);
      auto& sent = state.tiles[key];
      if (tile == sent) continue;
      auto now = tile ? tile->voxels() : std::vector<VoxelIndex>{};
      auto before = sent ? sent->voxels() : std::vector<VoxelIndex>{};
      std::sort(now.begin(), now.end());
      std::sort(before.begin(), before.end());
      std::set_difference(now.begin(), now.end(), before.begin(), before.end(),
                          std::back_inserter(add));
      std::set_difference(before.begin(), before.end(), now.begin(), now.end(),
                          std::back_inserter(remove));
      state.occupied += now.size();
      state.occupied -= before.size();
      if (tile) {
        sent = std::move(tile);
      } else {
        state.tiles.erase(key);
      }
    }
    if (inserted || !add.empty() || !remove.empty()) {
      out.push_back(
          voxelsMessage(session->id(), state.resolution, state.version, inserted, add, remove));
    }
    const auto new_poses = session->trajectory(state.poses_sent);
    if (!new_poses.empty()) {
      appendPoseMessages(session->id(), new_poses, false, out);
      state.poses_sent += new_poses.size();
    }
    // Status last, so that its counts are never ahead of the voxels already sent.
    SessionStatus status = session->status();
    status.occupied_voxels = state.occupied;
    std::string status_json = sessionJson(status, "session");
    if (status_json != state.status_json) {
      state.status_json = status_json;
      out.push_back(std::move(status_json));
    }
  }
  return out;
}

}  // namespace stereomap::core
