#include "tests/support/cluster_check.hpp"

#include <octomap/OcTree.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <memory>
#include <sstream>
#include <tuple>

#include "server/cluster/cluster_journal.hpp"
#include "server/cluster/cluster_recovery.hpp"
#include "tests/support/stream_count.hpp"

namespace stereomap::testing {

namespace {

// Every leaf of an .ot map at the finest depth: key -> log-odds.
std::map<std::tuple<int, int, int>, float> leaves(const std::string& ot) {
  std::istringstream in(ot);
  std::unique_ptr<octomap::AbstractOcTree> tree(octomap::AbstractOcTree::read(in));
  std::map<std::tuple<int, int, int>, float> out;
  auto* octree = dynamic_cast<octomap::OcTree*>(tree.get());
  if (octree == nullptr) return out;
  octree->expand();
  for (auto it = octree->begin_leafs(); it != octree->end_leafs(); ++it) {
    const auto key = it.getKey();
    out[{key[0], key[1], key[2]}] = it->getLogOdds();
  }
  return out;
}

// Poses of the --trajectory-out file `path` (TUM) and how many of them have no journaled pose
// with the same stamp (to the microsecond the text keeps).
std::pair<size_t, size_t> trajectoryAgainst(
    const std::string& path, const std::vector<proto::journal::JournalRecord>& records) {
  std::vector<int64_t> journaled_us;
  for (const auto& record : records) {
    if (const auto* pose = std::get_if<proto::PoseMsg>(&record)) {
      journaled_us.push_back((pose->stamp_ns + 500) / 1000);
    }
  }
  std::sort(journaled_us.begin(), journaled_us.end());
  std::istringstream lines(readText(path));
  size_t sent = 0, missing = 0;
  for (std::string line; std::getline(lines, line);) {
    if (line.empty() || line[0] == '#') continue;
    ++sent;
    const auto us = static_cast<int64_t>(std::llround(std::stod(line) * 1e6));
    const auto near = std::lower_bound(journaled_us.begin(), journaled_us.end(), us - 1);
    missing += near == journaled_us.end() || *near > us + 1;
  }
  return {sent, missing};
}

}  // namespace

bool FlightCheck::whole(bool with_map) const {
  return problem.empty() && sent_poses > 0 && lost() == 0 && repeated == 0 &&
         trajectory_missing == 0 && trajectory_poses == journaled_poses &&
         (!with_map || map_is_journals);
}

std::string FlightCheck::summary() const {
  std::ostringstream out;
  out << session << ": " << journaled_poses << "/" << sent_poses << " poses, " << journaled_clouds
      << "/" << sent_clouds << " clouds journaled, " << repeated << " repeated; trajectory "
      << trajectory_poses << " poses, " << trajectory_missing << " not journaled";
  if (live_leaves > 0) {
    out << "; live map " << live_leaves << " leaves, "
        << (map_is_journals ? "its journal's" : "NOT its journal's");
  }
  if (!problem.empty()) out << "; " << problem;
  return out.str();
}

FlightCheck checkFlight(ClusterHarness& cluster, int i, bool with_map,
                        std::chrono::seconds fuse_timeout) {
  FlightCheck check;
  check.session = "flight" + std::to_string(i);
  const Sent sent = sentBy(readText(cluster.vehicleLog(i)));
  check.sent_poses = sent.poses;
  check.sent_clouds = sent.clouds;
  auto journal = cluster::ClusterJournal::open(cluster.db().url());
  if (!journal) {
    check.problem = "cannot open the journal: " + journal.error().message;
    return check;
  }
  auto stored = (*journal)->read(check.session);
  if (!stored) {
    check.problem = "cannot read the session: " + stored.error().message;
    return check;
  }
  const auto journaled = samplesIn(stored->records);
  check.journaled_poses = journaled.poseCount();
  check.journaled_clouds = journaled.cloudCount();
  check.repeated = journaled.repeated;
  std::tie(check.trajectory_poses, check.trajectory_missing) =
      trajectoryAgainst(cluster.trajectoryOut(i), stored->records);
  if (!with_map) return check;

  // The live map, once its owner has fused everything it took ("" and a problem when it
  // cannot be had).
  const auto fromOwner = [&]() -> std::string {
    const auto owner = cluster.owners()[check.session];
    if (!cluster.servers().contains(owner)) {
      check.problem = "its owner '" + owner + "' is not a server of this cluster";
      return "";
    }
    auto& server = cluster.server(owner);
    const std::string path = "/api/sessions/" + check.session;
    if (!waitUntil(fuse_timeout, [&] {
          const auto reply = server.get(path);
          return reply.status == 200 &&
                 reply.body.find("\"fusion_backlog\":0") != std::string::npos;
        })) {
      check.problem = "its owner did not finish fusing it: " + server.get(path).body.substr(0, 300);
      return "";
    }
    const auto live = server.get(path + "/map.ot");
    if (live.status != 200) check.problem = "no live map: " + live.body.substr(0, 300);
    return live.status == 200 ? live.body : "";
  };
  std::string live_map = fromOwner();
  if (live_map.empty() &&
      cluster.query("SELECT state FROM sm_sessions WHERE id = '" + check.session + "'")
          .starts_with("ended")) {
    // Out of memory since its vehicle ended it (before or during this check): the map it
    // left with is its last snapshot, read again now; fused offline from every frame of the
    // journal, not from that snapshot.
    stored = (*journal)->read(check.session);
    if (!stored || stored->snapshot.empty()) {
      check.problem = "it left memory without a readable snapshot";
      return check;
    }
    check.problem.clear();
    live_map = std::move(stored->snapshot);
    stored->snapshot.clear();
  }
  if (live_map.empty()) return check;
  // Offline: the same records fused from scratch.
  core::MapServer scratch({.resolution = 0.1, .max_sessions = 1});
  size_t frames = 0, poses = 0;
  if (auto recovered = cluster::recoverSession(scratch, **journal, {check.session, "", 0, 0.1},
                                               *stored, frames, poses,
                                               /*wait_until_fused=*/true);
      !recovered) {
    check.problem = "cannot fuse it offline: " + recovered.error().message;
    return check;
  }
  auto offline = scratch.find(check.session)->mapFull();
  if (!offline) {
    check.problem = "no offline map: " + offline.error().message;
    return check;
  }
  const auto live_leaves = leaves(live_map);
  check.live_leaves = live_leaves.size();
  check.map_is_journals = live_leaves.size() > 1000 && live_leaves == leaves(*offline);
  return check;
}

std::vector<proto::journal::JournalRecord> recordedFlight(ClusterHarness& cluster,
                                                          const std::string& session) {
  std::vector<proto::journal::JournalRecord> flight;
  auto journal = cluster::ClusterJournal::open(cluster.db().url());
  if (!journal) return flight;
  auto stored = (*journal)->read(session);
  if (!stored) return flight;
  std::map<uint64_t, proto::CloudFrameMsg> clouds;  // whole, by record number
  (void)(*journal)->forEachFrame(
      session, 0, stored->last_number,
      [&](const proto::CloudFrameMsg& frame, uint64_t number) { clouds[number] = frame; });
  for (size_t i = 0; i < stored->records.size(); ++i) {
    if (std::holds_alternative<proto::PoseMsg>(stored->records[i])) {
      flight.push_back(stored->records[i]);
    } else if (auto it = clouds.find(stored->numbers[i]); it != clouds.end()) {
      flight.push_back(it->second);
    }
  }
  return flight;
}

}  // namespace stereomap::testing
