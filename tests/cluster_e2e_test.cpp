// Cross-process (issue 39): stereomap-server --cluster on a real PostgreSQL (started by the
// test, as an unprivileged user), real vehicles over loopback DDS. Two servers share four
// sessions; one is killed with SIGKILL mid-flight, or paused past its lease with SIGSTOP, or
// the database is killed and restarted under load. Every sample each vehicle sent must be
// journaled exactly once, and each session's live map must equal the map fused offline from
// its journal, voxel for voxel.
#include <gtest/gtest.h>
#include <octomap/OcTree.h>
#include <signal.h>
#include <nlohmann/json.hpp>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <cmath>
#include <map>
#include <regex>
#include <sstream>
#include <thread>

#include "server/cluster/cluster_journal.hpp"
#include "server/cluster/cluster_recovery.hpp"
#include "testing/data.hpp"
#include "tests/support/cluster_check.hpp"
#include "tests/support/cluster_harness.hpp"
#include "tests/support/stream_count.hpp"

namespace stereomap::testing {
namespace {

using namespace std::chrono_literals;
using Clock = std::chrono::steady_clock;

constexpr int kFailoverDomain = 103, kFencedDomain = 104, kDatabaseDomain = 105, kTilesDomain = 106,
              kRestartedDomain = 107, kHungDomain = 108, kPrimaryKilledDomain = 109,
              kPrimaryHungDomain = 110, kSilentDomain = 111, kManagedDomain = 112,
              kTokensDomain = 131;

class ClusterTest : public ::testing::Test {
 protected:
  // Nodes of the database under Patroni (0: one PostgreSQL).
  virtual int patroniNodes() const { return 0; }
  void SetUp() override {
    std::string why;
    cluster_ = ClusterHarness::start(&why, patroniNodes());
    // PostgreSQL, Patroni and etcd are installed by scripts/install-deps: their absence is a
    // failure, never a silent pass.
    if (!cluster_) GTEST_FAIL() << why;
  }
  void TearDown() override { cluster_.reset(); }

  ServerProcess& startServer(int domain, const std::string& id) {
    return cluster_->startServer(domain, id);
  }
  void startVehicle(int domain, int i, int frames) { cluster_->startVehicle(domain, i, frames); }
  std::string vehicleLog(int i) const { return cluster_->vehicleLog(i); }
  std::string query(const std::string& sql) { return cluster_->query(sql); }
  std::map<std::string, std::string> owners() { return cluster_->owners(); }
  void waitForVehicles() {
    std::string why;
    ASSERT_TRUE(cluster_->waitForVehicles(
        std::chrono::duration_cast<std::chrono::seconds>(scaledTimeout(180s)), &why))
        << why;
  }

  // Every vehicle's samples journaled once each, every pose of its --trajectory-out too; each
  // map, on the server that owns it, as fused offline from the journal.
  void expectWholeSessions(int count) {
    for (int i = 0; i < count; ++i) {
      const auto check = checkFlight(*cluster_, i, /*with_map=*/true);
      std::printf("%s\n", check.summary().c_str());
      EXPECT_TRUE(check.problem.empty()) << check.problem;
      EXPECT_GT(check.sent_poses, 0u);
      EXPECT_GT(check.trajectory_poses, 100u) << check.session;
      EXPECT_EQ(check.lost(), 0) << check.session;
      EXPECT_EQ(check.journaled_poses, check.sent_poses) << check.session;
      EXPECT_EQ(check.journaled_clouds, check.sent_clouds) << check.session;
      EXPECT_EQ(check.repeated, 0u) << check.session;
      EXPECT_EQ(check.trajectory_missing, 0u)
          << check.session << ": poses it sent that are not journaled";
      EXPECT_EQ(check.trajectory_poses, check.journaled_poses) << check.session;
      EXPECT_GT(check.live_leaves, 1000u) << check.session;
      EXPECT_TRUE(check.map_is_journals) << check.session << ": the live map is not its journal's";
    }
  }

  // The session as MCAP from its owner through the proxy, read from the cluster's database as
  // it is written: a whole file (its magic at both ends, its footer's summary) whose statistics
  // count a message at least for every journaled pose and cloud.
  void expectMcapThroughTheProxy(int port, const std::string& session) {
    const auto reply = httpGet(port, "/api/sessions/" + session + "/session.mcap");
    ASSERT_EQ(reply.status, 200) << reply.body.substr(0, 300);
    std::string file;
    if (reply.headers.find("chunked") != std::string::npos) {
      for (size_t at = 0;;) {  // chunk sizes in hex, each line ended by CRLF
        const size_t line_end = reply.body.find("\r\n", at);
        ASSERT_NE(line_end, std::string::npos);
        const size_t size = std::stoul(reply.body.substr(at, line_end - at), nullptr, 16);
        if (size == 0) break;
        file += reply.body.substr(line_end + 2, size);
        at = line_end + 2 + size + 2;
      }
    } else {
      file = reply.body;
    }
    const std::string magic("\x89MCAP0\r\n", 8);
    ASSERT_GT(file.size(), 1000u);
    ASSERT_EQ(file.substr(0, 8), magic);
    ASSERT_EQ(file.substr(file.size() - 8), magic);
    const auto u64 = [&](size_t at) {
      uint64_t v = 0;
      for (int i = 7; i >= 0; --i) v = (v << 8) | static_cast<uint8_t>(file[at + i]);
      return v;
    };
    const size_t footer = file.size() - 8 - 29;  // opcode, length, three fields
    ASSERT_EQ(file[footer], 0x02);
    uint64_t messages = 0;
    for (size_t at = u64(footer + 9); at < footer; at += 9 + u64(at + 1)) {
      if (file[at] == 0x0B) messages = u64(at + 9);  // Statistics: message_count first
    }
    auto journal = cluster::ClusterJournal::open(cluster_->db().url());
    ASSERT_TRUE(journal) << journal.error().message;
    auto stored = (*journal)->read(session);
    ASSERT_TRUE(stored) << stored.error().message;
    const auto journaled = samplesIn(stored->records);
    std::printf("%s as MCAP through the proxy: %zu bytes, %llu messages (%zu poses, %zu clouds)\n",
                session.c_str(), file.size(), static_cast<unsigned long long>(messages),
                journaled.poseCount(), journaled.cloudCount());
    EXPECT_GE(messages, journaled.poseCount() + journaled.cloudCount());
  }

  std::unique_ptr<ClusterHarness> cluster_;
};

// Two servers, four vehicles in four sessions (two each), one server killed mid-flight: the
// other owns every session within the lease and a moment, takes samples again, and in the end
// every sample was journaled once and every map is its journal's.
TEST_F(ClusterTest, AKilledServersSessionsAreTakenOverAndNothingIsLost) {
  startServer(kFailoverDomain, "a");
  startServer(kFailoverDomain, "b");
  for (int i = 0; i < 4; ++i) startVehicle(kFailoverDomain, i, 300);
  ASSERT_TRUE(waitUntil(30s, [&] { return owners().size() == 4; })) << query("TABLE sm_sessions");
  std::map<std::string, int> per_server;
  for (const auto& [session, owner] : owners()) ++per_server[owner];
  EXPECT_EQ(per_server["a"], 2);
  EXPECT_EQ(per_server["b"], 2);

  // One URL for operators and viewers: nginx in front of both servers.
  std::string why;
  ASSERT_TRUE(cluster_->startNginx(&why)) << why;
  auto* nginx = &cluster_->nginx();
  std::this_thread::sleep_for(8s);
  const auto listed = httpGet(nginx->port(), "/api/sessions");
  for (int i = 0; i < 4; ++i) {
    EXPECT_NE(listed.body.find("\"flight" + std::to_string(i) + "\""), std::string::npos)
        << "every session of the cluster is listed through the proxy: " << listed.body;
  }
  for (int i = 0; i < 4; ++i) {
    const std::string path = "/api/sessions/flight" + std::to_string(i);
    EXPECT_EQ(httpGet(nginx->port(), path).status, 200) << path << " reaches its owner";
  }
  ASSERT_TRUE(viewerSeesTiles(nginx->port(), "flight0", 10s)) << nginx->accessLog();

  const std::string victim = owners()["flight0"];
  const std::string survivor = victim == "a" ? "b" : "a";
  cluster_->server(victim).process().kill9();
  const auto killed = Clock::now();
  ASSERT_TRUE(waitUntil(
      30s, [&] { return cluster_->allOwnedBy(survivor); }, 100ms));
  const double failover_s = std::chrono::duration<double>(Clock::now() - killed).count();
  // Ingest resumed: a sample of each taken session committed with the new epoch.
  ASSERT_TRUE(waitUntil(
      30s,
      [&] {
        // Placed at epoch 1 and adopted at 2; taken at 3 and adopted again at 4.
        return query("SELECT count(DISTINCT session) FROM sm_journal WHERE epoch > 2") == "2\n";
      },
      100ms));
  const double resumed_s = std::chrono::duration<double>(Clock::now() - killed).count();
  // A viewer of the killed server's session, reconnecting through the proxy, sees it again.
  ASSERT_TRUE(waitUntil(
      60s, [&] { return viewerSeesTiles(nginx->port(), "flight0", 2s); }, 200ms))
      << nginx->accessLog();
  const double viewer_s = std::chrono::duration<double>(Clock::now() - killed).count();
  std::printf("failover %.1f s, ingest resumed %.1f s, viewer back %.1f s\n", failover_s, resumed_s,
              viewer_s);
  EXPECT_LT(failover_s, 7.0);
  EXPECT_LT(resumed_s, 10.0);
  EXPECT_LT(viewer_s, 15.0);

  waitForVehicles();
  expectWholeSessions(4);
  expectMcapThroughTheProxy(nginx->port(), "flight0");
}

// A server paused past its lease (SIGSTOP) loses its sessions to the other; woken (SIGCONT),
// it commits nothing with its old epoch, says it was fenced, and unloads them; the sessions
// end whole on their new owner.
TEST_F(ClusterTest, AStaleOwnerIsFencedAndCommitsNothing) {
  startServer(kFencedDomain, "a");
  startServer(kFencedDomain, "b");
  for (int i = 0; i < 2; ++i) startVehicle(kFencedDomain, i, 250);
  ASSERT_TRUE(waitUntil(30s, [&] { return owners().size() == 2; }));
  std::this_thread::sleep_for(5s);
  const std::string stale = owners()["flight0"];
  const std::string other = stale == "a" ? "b" : "a";
  ::kill(cluster_->server(stale).process().pid(), SIGSTOP);
  ASSERT_TRUE(waitUntil(30s, [&] { return cluster_->allOwnedBy(other); }));
  std::this_thread::sleep_for(2s);  // the new owner takes samples
  ::kill(cluster_->server(stale).process().pid(), SIGCONT);
  // Unloaded: it answers for neither session any more (its listing names their new server).
  ASSERT_TRUE(waitUntil(20s, [&] {
    return cluster_->server(stale).get("/api/sessions/flight0").status == 404 &&
           cluster_->server(stale).get("/api/sessions/flight1").status == 404;
  })) << cluster_->server(stale).get("/api/sessions").body;
  const std::string log = cluster_->server(stale).log();
  EXPECT_NE(log.find("fenced"), std::string::npos) << log;
  waitForVehicles();
  // Rows written with an epoch that was no longer the session's: none.
  EXPECT_EQ(query("SELECT count(*) FROM sm_journal j JOIN sm_sessions s ON s.id = j.session "
                  "WHERE j.epoch < s.epoch AND j.committed_at >= s.owned_since"),
            "0\n");
  EXPECT_TRUE(cluster_->server(stale).process().running()) << "fenced, not dead";
  expectWholeSessions(2);
}

// The database killed under load (the postmaster and its backends: commits under way lose
// their answers) and started again: the servers stay up, refuse samples meanwhile (the
// vehicles keep them), and take them again by themselves; a group committed without its
// answer is undone before the session's next write (ClusterJournal's doubt).
TEST_F(ClusterTest, TheDatabaseRestartedUnderLoadLosesNothing) {
  startServer(kDatabaseDomain, "a");
  startServer(kDatabaseDomain, "b");
  for (int i = 0; i < 2; ++i) startVehicle(kDatabaseDomain, i, 300);
  ASSERT_TRUE(waitUntil(30s, [&] { return owners().size() == 2; }));
  std::this_thread::sleep_for(6s);
  cluster_->db().crash();
  std::this_thread::sleep_for(5s);
  std::string why;
  ASSERT_TRUE(cluster_->db().restart(&why)) << why;
  waitForVehicles();
  for (const auto& [id, server] : cluster_->servers()) {
    EXPECT_TRUE(server->process().running()) << id;
    EXPECT_EQ(server->get("/healthz").status, 200) << id << ": " << server->log();
  }
  expectWholeSessions(2);
}

// The fault that lost acknowledged samples (106 of 600 poses): a server paused (a hung process,
// a VM paused), a new process started under the same --server-id, the old one resumed. The
// new process adopts the session at a new epoch; the old one, resumed, commits nothing, finds
// itself superseded and exits; every pose the vehicle sent is journaled once.
TEST_F(ClusterTest, AServerRestartedUnderItsIdWhileTheOldOneIsPausedLosesNothing) {
  auto& old_process = cluster_->startServer(kRestartedDomain, "a", 2, "a-paused");
  startVehicle(kRestartedDomain, 0, 400);
  ASSERT_TRUE(waitUntil(30s, [&] { return owners().size() == 1; }));
  std::this_thread::sleep_for(8s);
  ::kill(old_process.process().pid(), SIGSTOP);
  startServer(kRestartedDomain, "a");  // the same id, as a supervisor restarts a hung server
  ASSERT_TRUE(waitUntil(30s, [&] {
    return cluster_->server("a").get("/api/sessions/flight0").status == 200;
  })) << cluster_->server("a").log();
  std::this_thread::sleep_for(8s);
  ::kill(old_process.process().pid(), SIGCONT);
  const auto exit_code = old_process.process().waitExit(30s);
  ASSERT_TRUE(exit_code.has_value()) << "the superseded process is still running";
  EXPECT_EQ(*exit_code, 1);
  const std::string log = old_process.log();
  EXPECT_NE(log.find("superseded"), std::string::npos) << log;
  EXPECT_EQ(log.find("23505"), std::string::npos) << log;
  waitForVehicles();
  EXPECT_NE(readText(vehicleLog(0)).find("0 still unacknowledged"), std::string::npos)
      << readText(vehicleLog(0));
  // Each adoption had its own epoch: rows of every epoch are the vehicle's, none repeated.
  EXPECT_EQ(query("SELECT count(*) FROM sm_journal j JOIN sm_sessions s ON s.id = j.session "
                  "WHERE j.epoch < s.epoch AND j.committed_at >= s.owned_since"),
            "0\n");
  expectWholeSessions(1);
}

// The database hung (every process stopped: TCP answers, SQL does not) under flying vehicles:
// /healthz says so within 3 s on every server, viewers go on being served from memory, and
// once it resumes everything goes on by itself with nothing lost.
TEST_F(ClusterTest, AHungDatabaseIsSeenWithinThreeSecondsAndEverythingResumes) {
  startServer(kHungDomain, "a");
  startServer(kHungDomain, "b");
  for (int i = 0; i < 2; ++i) startVehicle(kHungDomain, i, 300);
  ASSERT_TRUE(waitUntil(30s, [&] { return owners().size() == 2; }));
  std::this_thread::sleep_for(6s);
  const auto owner = owners();
  cluster_->db().pause();
  const auto hung = Clock::now();
  std::map<std::string, double> seen_s;
  while (seen_s.size() < 2 && Clock::now() - hung < 10s) {
    for (const auto& [id, server] : cluster_->servers()) {
      if (!seen_s.contains(id) && server->get("/healthz").status != 200) {
        seen_s[id] = std::chrono::duration<double>(Clock::now() - hung).count();
      }
    }
    std::this_thread::sleep_for(100ms);
  }
  for (const auto& [id, server] : cluster_->servers()) {
    ASSERT_TRUE(seen_s.contains(id)) << id << ": /healthz stayed 200 with the database hung";
    std::printf("server %s degraded %.1f s after the database hung\n", id.c_str(), seen_s[id]);
    EXPECT_LT(seen_s[id], 3.0) << id;
  }
  auto& flight0_owner = cluster_->server(owner.at("flight0"));
  EXPECT_TRUE(viewerSeesTiles(flight0_owner.port(), "flight0", 5s))
      << "viewers are served from memory meanwhile";
  std::this_thread::sleep_for(12s - (Clock::now() - hung));
  cluster_->db().resume();
  const auto resumed = Clock::now();
  ASSERT_TRUE(waitUntil(20s, [&] {
    for (const auto& [id, server] : cluster_->servers()) {
      if (server->get("/healthz").status != 200) return false;
    }
    return true;
  })) << cluster_->server("a").log();
  std::printf("healthy again %.1f s after the database resumed\n",
              std::chrono::duration<double>(Clock::now() - resumed).count());
  waitForVehicles();
  expectWholeSessions(2);
}

// The database failing over: three PostgreSQL nodes under Patroni, synchronous replication
// (a sample is acknowledged only once a standby has it), the servers on one multi-host URL.
// The state the database gives session `id` ("" when it has none).
std::string stateOf(ClusterHarness& cluster, const std::string& id) {
  auto state = cluster.query("SELECT state FROM sm_sessions WHERE id = '" + id + "'");
  while (!state.empty() && std::isspace(static_cast<unsigned char>(state.back()))) state.pop_back();
  return state;
}

bool waitForState(ClusterHarness& cluster, const std::string& id, const std::string& state,
                  std::chrono::seconds timeout) {
  const auto deadline = Clock::now() + scaledTimeout(timeout);
  while (Clock::now() < deadline) {
    if (stateOf(cluster, id) == state) return true;
    std::this_thread::sleep_for(200ms);
  }
  return false;
}

// A vehicle cut off (paused) past --vehicle-timeout: its session ends, leaves the server's
// memory (snapshotted, 'ended' in the database, listed with its counts), and is served again
// when the vehicle comes back holding samples nobody acknowledged; nothing is lost.
TEST_F(ClusterTest, ASilentVehiclesSessionLeavesMemoryAndIsServedAgainWhenItReturns) {
  auto& server = cluster_->startServer(kSilentDomain, "a", 2, "", {"--vehicle-timeout", "2"});
  startVehicle(kSilentDomain, 0, 350);
  const auto deadline = Clock::now() + scaledTimeout(30s);
  while (owners()["flight0"] != "a" && Clock::now() < deadline) std::this_thread::sleep_for(100ms);
  ASSERT_EQ(owners()["flight0"], "a");
  std::this_thread::sleep_for(4s);
  signalWithChildren(cluster_->vehicle(0).pid(), SIGSTOP);
  // Silent for 2 s: ended; quiet for 10 s more: out of memory.
  const bool ended = waitForState(*cluster_, "flight0", "ended", 30s);
  const auto listing = server.get("/api/sessions");
  const auto metrics = server.get("/metrics").body;
  signalWithChildren(cluster_->vehicle(0).pid(), SIGCONT);
  ASSERT_TRUE(ended) << "state " << stateOf(*cluster_, "flight0") << "\n" << server.log();
  EXPECT_EQ(seriesValue(metrics, "stereomap_cluster_sessions_served"), 0.0);
  ASSERT_EQ(listing.status, 200);
  const auto sessions = nlohmann::json::parse(listing.body);
  ASSERT_EQ(sessions.size(), 1u) << listing.body;
  EXPECT_EQ(sessions[0]["state"], "ended");
  EXPECT_GT(sessions[0]["poses"].get<int>(), 10) << "its counts, as it left memory";
  EXPECT_GE(std::stoi(query("SELECT count(*) FROM sm_snapshots WHERE session = 'flight0'")), 1)
      << "snapshotted as it left";

  // Back, still flying: its start event reaches the servers again (DDS delivers it to a
  // vehicle rediscovered after its pause; a vehicle that stayed discovered sends it again every
  // 2 s: pipeline_test), the session is served again within seconds, not at the vehicle's end
  // event, and the vehicle sends what waited.
  EXPECT_TRUE(waitForState(*cluster_, "flight0", "live", 10s));
  EXPECT_FALSE(cluster_->vehicle(0).waitExit(0s).has_value()) << "served again while it flies";
  waitForVehicles();
  EXPECT_EQ(stateOf(*cluster_, "flight0"), "live");
  expectWholeSessions(1);
  const auto log = server.log();
  EXPECT_NE(log.find("out of this server's memory"), std::string::npos);
}

// Operators' work in a cluster, through the proxy and with stereomap-store --cluster: a flight
// that ended is closed, opened read-only (its tiles served wherever it was opened), merged
// with another, replayed as the MCAP of the tool, checked and deleted.
TEST_F(ClusterTest, OperatorsCloseOpenMergeExportAndDeleteSessionsInTheCluster) {
  startServer(kManagedDomain, "a");
  startServer(kManagedDomain, "b");
  std::string why;
  ASSERT_TRUE(cluster_->startNginx(&why)) << why;
  const int proxy = cluster_->nginx().port();
  startVehicle(kManagedDomain, 0, 120);
  startVehicle(kManagedDomain, 1, 120);
  waitForVehicles();
  // Ended by their vehicles, then out of memory.
  ASSERT_TRUE(waitForState(*cluster_, "flight0", "ended", 40s)) << stateOf(*cluster_, "flight0");
  ASSERT_TRUE(waitForState(*cluster_, "flight1", "ended", 40s));
  const auto journaled = [&](const std::string& id) {
    return std::stoi(
        query("SELECT count(*) FROM sm_journal WHERE session = '" + id + "' AND kind = 1"));
  };
  const int clouds0 = journaled("flight0"), clouds1 = journaled("flight1");

  // Every server routes to where a session was opened from its next control round on, and the
  // proxy keeps a route a second: a viewer that came too early connects again.
  const auto seesTiles = [&](const std::string& id) {
    const auto deadline = Clock::now() + 20s;
    while (Clock::now() < deadline) {
      if (viewerSeesTiles(proxy, id, 5s)) return true;
      std::this_thread::sleep_for(500ms);
    }
    return false;
  };
  auto post = [&](const std::string& path, const std::string& body = "") {
    return httpRequest(proxy, "POST", path, body);
  };
  auto closed = post("/api/sessions/flight0/close");
  EXPECT_EQ(closed.status, 200) << closed.body;
  EXPECT_EQ(stateOf(*cluster_, "flight0"), "closed");
  EXPECT_EQ(post("/api/sessions/flight0/close").status, 409) << "closed once";
  {
    // A vehicle flying into the closed session: no server reads it, each answers its
    // announcement; the vehicle says so once and gives up (exit 3).
    const std::string log = cluster_->dir() + "/late-vehicle.log";
    ChildProcess late(userVehicleArgs(kManagedDomain, "flight0", 60, "memory",
                                      {"--vehicle", "late", "--flush-timeout", "5"}),
                      log);
    EXPECT_EQ(late.waitExit(60s).value_or(-1), 3) << readText(log);
    EXPECT_NE(readText(log).find("session 'flight0' was closed by the server (session 'flight0' "
                                 "was closed by an operator"),
              std::string::npos)
        << readText(log);
    EXPECT_EQ(stateOf(*cluster_, "flight0"), "closed") << "not revived by its vehicle";
  }
  auto opened = post("/api/sessions/flight0/open");
  ASSERT_EQ(opened.status, 200) << opened.body;
  EXPECT_EQ(nlohmann::json::parse(opened.body)["state"], "opened") << opened.body;
  EXPECT_EQ(stateOf(*cluster_, "flight0"), "opened");
  EXPECT_TRUE(seesTiles("flight0")) << "routed to where it was opened";

  auto merged =
      post("/api/sessions/merge", R"({"first": "flight0", "second": "flight1", "into": "both"})");
  ASSERT_EQ(merged.status, 200) << merged.body;
  EXPECT_EQ(journaled("both"), clouds0 + clouds1);
  // The other servers route to it from their next control round on.
  const auto routed = [&](const std::string& path) {
    const auto deadline = Clock::now() + 3s;
    auto reply = httpGet(proxy, path);
    while (reply.status == 404 && Clock::now() < deadline) {
      std::this_thread::sleep_for(100ms);
      reply = httpGet(proxy, path);
    }
    return reply;
  };
  const auto both = routed("/api/sessions/both");
  ASSERT_EQ(both.status, 200) << both.body;
  EXPECT_EQ(nlohmann::json::parse(both.body).value("frames", -1), clouds0 + clouds1) << both.body;
  EXPECT_TRUE(seesTiles("both"));

  auto removed = httpRequest(proxy, "DELETE", "/api/sessions/flight1");
  EXPECT_EQ(removed.status, 200) << removed.body;
  EXPECT_EQ(stateOf(*cluster_, "flight1"), "");
  EXPECT_EQ(journaled("flight1"), 0) << "its journal went with it";

  // The tool, beside the running servers.
  const auto tool = [&](std::vector<std::string> args) {
    args.insert(args.begin(), {std::string(STEREOMAP_BIN_DIR) + "/stereomap-store", "--cluster",
                               cluster_->db().url()});
    return runTool(args);
  };
  const auto listed = tool({"list"});
  EXPECT_EQ(listed.exit_code, 0) << listed.output;
  EXPECT_NE(listed.output.find("both"), std::string::npos) << listed.output;
  EXPECT_NE(listed.output.find("opened"), std::string::npos) << listed.output;
  const auto checked = tool({"check"});
  EXPECT_EQ(checked.exit_code, 0) << checked.output;
  const auto shown = tool({"show", "flight0"});
  ASSERT_EQ(shown.exit_code, 0) << shown.output;
  EXPECT_EQ(nlohmann::json::parse(shown.output).value("frames", -1), clouds0) << shown.output;
  const std::string mcap = cluster_->dir() + "/both.mcap";
  const auto exported = tool({"export", "both", "--mcap", mcap});
  ASSERT_EQ(exported.exit_code, 0) << exported.output;
  EXPECT_EQ(readText(mcap).substr(0, 8), std::string("\x89MCAP0\r\n", 8));
  const std::string ply = cluster_->dir() + "/flight0.ply";
  EXPECT_EQ(tool({"export", "flight0", "--format", "ply", "--out", ply}).exit_code, 0);
  EXPECT_NE(readText(ply).find("end_header"), std::string::npos);
  const auto merged_again = tool({"merge", "flight0", "both", "--into", "all"});
  EXPECT_EQ(merged_again.exit_code, 0) << merged_again.output;
  // Compacted once closed: its map and poses kept, its clouds' points gone.
  EXPECT_EQ(tool({"close", "flight0"}).exit_code, 0);
  const auto compacted = tool({"compact", "flight0"});
  EXPECT_EQ(compacted.exit_code, 0) << compacted.output;
  EXPECT_NE(compacted.output.find(std::to_string(clouds0) + " clouds compacted"), std::string::npos)
      << compacted.output;
  const auto shown_again = tool({"show", "flight0"});
  ASSERT_EQ(shown_again.exit_code, 0) << shown_again.output;
  const auto again = nlohmann::json::parse(shown_again.output);
  EXPECT_EQ(again.value("occupied_voxels", -1),
            nlohmann::json::parse(shown.output).value("occupied_voxels", -2))
      << "the same map, from its snapshot";
  EXPECT_EQ(again.value("poses", -1), nlohmann::json::parse(shown.output).value("poses", -2));
  EXPECT_EQ(tool({"close", "both"}).exit_code, 0);
  EXPECT_EQ(stateOf(*cluster_, "both"), "closed");
  const auto refused = tool({"delete", "nothing", "--yes"});
  EXPECT_NE(refused.exit_code, 0);
  EXPECT_NE(refused.output.find("no session 'nothing'"), std::string::npos) << refused.output;
  EXPECT_EQ(tool({"delete", "both", "--yes"}).exit_code, 0);
  EXPECT_EQ(stateOf(*cluster_, "both"), "");
  // Every server lets it go at its next round that reads the cluster (0.2-0.3 s here). Each
  // is asked itself: through the proxy, a deleted session goes to any server, and the first
  // 404 from one that had read the delete ended the wait while another had not yet (the
  // flake of 1 run in 3-6 until 2026-12-06).
  const auto deleted = Clock::now();
  const auto gone = deleted + 5s;
  const auto everyServerLetGo = [&] {
    for (const auto& [id, server] : cluster_->servers()) {
      if (server->get("/api/sessions/both").status != 404) return false;
    }
    return true;
  };
  while (!everyServerLetGo() && Clock::now() < gone) std::this_thread::sleep_for(100ms);
  EXPECT_EQ(httpGet(proxy, "/api/sessions/both").status, 404);
  std::printf("deleted session let go after %.1f s\n",
              std::chrono::duration<double>(Clock::now() - deleted).count());
  for (const auto& [id, server] : cluster_->servers()) {
    const auto direct = server->get("/api/sessions/both");
    EXPECT_EQ(direct.status, 404) << id << ": " << direct.body;
    if (direct.status != 404) {  // where its control thread is, for the log
      try {
        const auto stacks = runTool({"/usr/bin/gdb", "-p", std::to_string(server->process().pid()),
                                     "-batch", "-ex", "thread apply all bt"});
        std::printf("--- %s's threads\n%s\n", id.c_str(), stacks.output.c_str());
      } catch (const std::exception& e) {
        std::printf("--- %s's threads: %s\n", id.c_str(), e.what());
      }
    }
  }
  if (HasFailure()) {
    for (const auto& [id, server] : cluster_->servers()) {
      std::printf("--- server %s\n%s\n", id.c_str(), server->log().c_str());
    }
  }
}

class PatroniClusterTest : public ClusterTest {
 protected:
  int patroniNodes() const override { return 3; }

  // The database's clock now (before a fault: it may not answer after).
  std::string databaseNow() {
    const std::string now = query("SELECT clock_timestamp()");
    return now.substr(0, now.find('\n'));
  }
  // Seconds from `since` until a sample of every session is committed later than `after` (the
  // database's clock, read just before the fault).
  double ingestResumed(Clock::time_point since, const std::string& after, int sessions) {
    if (!waitUntil(
            60s,
            [&] {
              return query("SELECT count(DISTINCT session) FROM sm_journal WHERE committed_at > '" +
                           after + "'") == std::to_string(sessions) + "\n";
            },
            100ms)) {
      return -1;
    }
    return std::chrono::duration<double>(Clock::now() - since).count();
  }
};

// The primary's PostgreSQL killed under flying vehicles: a synchronous standby takes over
// (Patroni), the servers find it on their own, and nothing a vehicle was told is journaled is
// lost; the killed node comes back as a standby.
TEST_F(PatroniClusterTest, ThePrimaryKilledUnderLoadLosesNothing) {
  startServer(kPrimaryKilledDomain, "a");
  startServer(kPrimaryKilledDomain, "b");
  for (int i = 0; i < 2; ++i) startVehicle(kPrimaryKilledDomain, i, 300);
  ASSERT_TRUE(waitUntil(30s, [&] { return owners().size() == 2; }));
  std::this_thread::sleep_for(6s);
  const std::string before = databaseNow();
  cluster_->db().crash();
  const auto killed = Clock::now();
  const double resumed_s = ingestResumed(killed, before, 2);
  std::printf("database failover: ingest resumed %.1f s after the primary was killed\n", resumed_s);
  EXPECT_GT(resumed_s, 0) << "ingest never resumed";
  EXPECT_LT(resumed_s, 15.0);
  std::string why;
  ASSERT_TRUE(cluster_->db().restart(&why)) << why;
  waitForVehicles();
  expectWholeSessions(2);
}

// The primary hung (its PostgreSQL stopped, Patroni not) for 20 s: /healthz says so within 3 s,
// Patroni fails over once the primary's leader key runs out, ingest resumes before the hang
// ends, and the old primary, resumed, can commit nothing it would lose: it rejoins as a
// standby. Nothing acknowledged is lost.
TEST_F(PatroniClusterTest, APrimaryHungForTwentySecondsIsFailedOverAndLosesNothing) {
  startServer(kPrimaryHungDomain, "a");
  startServer(kPrimaryHungDomain, "b");
  for (int i = 0; i < 2; ++i) startVehicle(kPrimaryHungDomain, i, 400);
  ASSERT_TRUE(waitUntil(30s, [&] { return owners().size() == 2; }));
  std::this_thread::sleep_for(6s);
  const std::string before = databaseNow();
  cluster_->db().pause();
  const auto hung = Clock::now();
  EXPECT_TRUE(waitUntil(
      3s, [&] { return cluster_->server("a").get("/healthz").status != 200; }, 100ms))
      << "/healthz stayed 200 with the primary hung";
  const double resumed_s = ingestResumed(hung, before, 2);
  std::printf("hung primary: ingest resumed %.1f s after it hung\n", resumed_s);
  EXPECT_GT(resumed_s, 0) << "ingest never resumed";
  EXPECT_LT(resumed_s, 20.0) << "resumed only with the hung primary";
  std::this_thread::sleep_for(20s - (Clock::now() - hung));
  cluster_->db().resume();
  std::string why;
  ASSERT_TRUE(cluster_->db().restart(&why)) << why;
  waitForVehicles();
  expectWholeSessions(2);
}

// A --cluster URL that cannot be reached, or whose credentials are refused, is a clear error
// at start.
TEST_F(ClusterTest, AnUnreachableOrRefusedDatabaseIsAClearErrorAtStart) {
  const std::string server = std::string(STEREOMAP_BIN_DIR) + "/stereomap-server";
  const auto unreachable =
      runTool({server, "--http", "127.0.0.1:0", "--cluster",
               "postgresql://stereomap@127.0.0.1:" + std::to_string(unusedPort()) + "/postgres"},
              30s);
  EXPECT_EQ(unreachable.exit_code, 1) << unreachable.output;
  EXPECT_NE(unreachable.output.find("cannot be reached"), std::string::npos) << unreachable.output;
  const std::string wrong_password = std::regex_replace(
      cluster_->db().url(), std::regex("^(postgresql://[^:]*):[^@]*@"), "$1:not-the-password@");
  const auto refused = runTool({server, "--http", "127.0.0.1:0", "--cluster", wrong_password}, 30s);
  EXPECT_EQ(refused.exit_code, 1) << refused.output;
  EXPECT_NE(refused.output.find("refused the credentials"), std::string::npos) << refused.output;
  EXPECT_EQ(refused.output.find("not-the-password"), std::string::npos) << "the password is shown";
}

// A campus-sized map imported into the cluster and served by one of its servers: fifty clients
// fetch every tile (every level, at its versioned URL) through nginx, twice. The second pass
// comes from nginx's cache: the servers are asked only where each tile lives (the token check).
TEST_F(ClusterTest, FiftyClientsFetchACampusTwiceAndTheSecondPassIsNginxs) {
  const std::filesystem::path campus = kDataDir / "octomap_samples" / "fr_campus.bt";
  STEREOMAP_SKIP_WITHOUT(campus);
  startServer(kTilesDomain, "a");
  startServer(kTilesDomain, "b");
  const auto imported =
      runTool({std::string(STEREOMAP_BIN_DIR) + "/stereomap-store", "--cluster",
               cluster_->db().url(), "import", campus.string(), "--session", "campus"},
              120s);
  ASSERT_EQ(imported.exit_code, 0) << imported.output;
  EXPECT_EQ(imported.output.find(cluster_->db().url()), std::string::npos)
      << "the password is shown";
  std::string why;
  ASSERT_TRUE(cluster_->startNginx(&why)) << why;
  auto* nginx = &cluster_->nginx();
  // Taken by a server and restored from its snapshot: every tile listed.
  std::vector<std::string> urls;
  ASSERT_TRUE(waitUntil(60s, [&] {
    const auto index = httpGet(nginx->port(), "/api/sessions/campus/tiles");
    if (index.status != 200) return false;
    urls.clear();
    const auto listed = nlohmann::json::parse(index.body);  // kept: the loop reads into it
    for (const auto& tile : listed["tiles"]) urls.push_back(tile["url"]);
    return urls.size() == 2772;  // 396 tiles at each of 7 levels
  })) << urls.size();

  constexpr int kClients = 50;
  struct Pass {
    std::atomic<size_t> ok = 0, hits = 0;
  };
  Pass passes[2];
  for (auto& pass : passes) {
    std::vector<std::thread> clients;
    for (int c = 0; c < kClients; ++c) {
      clients.emplace_back([&, c] {
        HttpConnection connection(nginx->port());
        // Each client in its own order, as viewers looking at different places would.
        for (size_t i = 0; i < urls.size(); ++i) {
          const auto reply = connection.get(urls[(i + static_cast<size_t>(c) * 53) % urls.size()]);
          if (reply.status != 200) continue;
          ++pass.ok;
          if (reply.header("X-Cache-Status") == "HIT") ++pass.hits;
        }
      });
    }
    for (auto& client : clients) client.join();
  }
  const size_t total = urls.size() * kClients;
  const double second_hits = 100.0 * static_cast<double>(passes[1].hits) / total;
  std::printf(
      "%zu tiles, %d clients: first pass %zu ok, %zu hits; second pass %zu ok, %.1f %% hits\n",
      urls.size(), kClients, passes[0].ok.load(), passes[0].hits.load(), passes[1].ok.load(),
      second_hits);
  EXPECT_EQ(passes[0].ok, total);
  EXPECT_EQ(passes[1].ok, total);
  EXPECT_GE(second_hits, 95.0);
}

// nginx's caches never answer a client that lacks the token they were filled with (issue 55):
// a tile a viewer just fetched (kept by nginx at its versioned URL) and the session's route are
// refused to a client without a token, or with a wrong one, while the viewer is served from the
// cache.
TEST_F(ClusterTest, ATokenlessClientNeverGetsWhatATokenHolderJustFetched) {
  const std::string tokens = cluster_->dir() + "/tokens";
  const auto made = runTool(
      {std::string(STEREOMAP_BIN_DIR) + "/stereomap-certs", "token", tokens, "viewer", "wall"});
  ASSERT_EQ(made.exit_code, 0) << made.output;
  const std::string token = made.output.substr(0, made.output.find('\n'));
  const std::string bearer = "Authorization: Bearer " + token + "\r\n";
  cluster_->startServer(kTokensDomain, "a", 2, "", {"--tokens", tokens});
  std::string why;
  ASSERT_TRUE(cluster_->startNginx(&why)) << why;
  const int proxy = cluster_->nginx().port();
  startVehicle(kTokensDomain, 0, 40);
  std::string url;
  ASSERT_TRUE(waitUntil(60s, [&] {
    const auto index = httpRequest(proxy, "GET", "/api/sessions/flight0/tiles", "", bearer);
    if (index.status != 200) return false;
    const auto listed = nlohmann::json::parse(index.body);
    if (listed["tiles"].empty()) return false;
    url = listed["tiles"][0]["url"];
    return true;
  })) << cluster_->nginx().accessLog();
  waitForVehicles();  // the tile's version stays: nothing changes it after the flight
  const auto index = nlohmann::json::parse(
      httpRequest(proxy, "GET", "/api/sessions/flight0/tiles", "", bearer).body);
  url = index["tiles"][0]["url"];
  ASSERT_NE(url.find("v="), std::string::npos) << url;
  for (int i = 0; i < 2; ++i) {
    EXPECT_EQ(httpRequest(proxy, "GET", url, "", bearer).status, 200);
  }
  const auto cached = httpRequest(proxy, "GET", url, "", bearer);
  EXPECT_EQ(cached.status, 200);
  EXPECT_EQ(cached.header("X-Cache-Status"), "HIT") << "the test needs nginx to keep the tile";
  const std::string sep = url.find('?') == std::string::npos ? "?" : "&";
  for (const auto& [path, headers] : {std::pair{url, std::string()},
                                      {url + sep + "token=guess", ""},
                                      {url, "Authorization: Bearer guess\r\n"},
                                      {"/api/sessions/flight0", ""},
                                      {"/api/sessions/flight0/tiles", ""}}) {
    const auto reply = httpRequest(proxy, "GET", path, "", headers);
    EXPECT_EQ(reply.status, 401) << path << " " << headers << ": " << reply.body.substr(0, 200);
  }
  EXPECT_EQ(httpGet(proxy, url + sep + "token=" + token).status, 200);
}

}  // namespace
}  // namespace stereomap::testing
