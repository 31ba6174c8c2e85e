// Session management across real processes (issue 5): two sim flights stream to
// stereomap-server over DDS; the REST API closes, opens, merges and deletes sessions; then
// stereomap-store works on the same store offline, and refuses to write while a server
// holds it.
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <filesystem>
#include <fstream>
#include <regex>

#include "common/time.hpp"
#include "tests/support/server_fixture.hpp"
#include "tests/support/stream_count.hpp"

namespace stereomap::testing {
namespace {

using namespace std::chrono_literals;
using nlohmann::json;
namespace fs = std::filesystem;

constexpr int kDomain = 75;

json status(const ServerProcess& server, const std::string& id) {
  const auto reply = server.get("/api/sessions/" + id);
  return reply.status == 200 ? json::parse(reply.body) : json();
}

// Flies `frames` sim frames into `session` and waits until the server has fused them all.
void fly(const ServerProcess& server, const std::string& session, int frames) {
  ChildProcess onboard(onboardArgs(kDomain, session, frames, {"--rate", "20"}),
                       server.store() + "." + session + ".log");
  ASSERT_EQ(onboard.waitExit(120s).value_or(-1), 0) << "onboard failed";
  ASSERT_TRUE(waitUntil(60s, [&] {
    const auto s = status(server, session);
    return s.is_object() && s["state"] == "ended" && s["frames"] == frames &&
           s["fusion_backlog"] == 0;
  })) << server.log();
}

ToolRun store(const std::string& root, std::vector<std::string> args) {
  args.insert(args.begin(), {std::string(STEREOMAP_BIN_DIR) + "/stereomap-store", "--store", root});
  return runTool(args);
}

std::string readFile(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

TEST(SessionAdmin, RestAndOfflineToolManageStoredSessions) {
  const std::string root = makeTempDir("stereomap-admin-store");
  {
    ServerProcess server(kDomain, {"--resolution", "0.1"}, root);
    fly(server, "f1", 12);
    fly(server, "f2", 8);
    const auto f1 = status(server, "f1");

    // Close: saved and unloaded; its exports wait for an open.
    auto reply = server.request("POST", "/api/sessions/f1/close");
    ASSERT_EQ(reply.status, 200) << reply.body;
    EXPECT_EQ(json::parse(reply.body)["state"], "closed");
    EXPECT_EQ(server.request("POST", "/api/sessions/f1/close").status, 409);
    EXPECT_EQ(server.get("/api/sessions/f1/map.bt").status, 409);
    const auto list = json::parse(server.get("/api/sessions").body);
    ASSERT_EQ(list.size(), 2u);
    EXPECT_EQ(list[1]["id"], "f1");
    EXPECT_EQ(list[1]["state"], "closed");
    EXPECT_EQ(list[1]["occupied_voxels"], f1["occupied_voxels"]);

    // Open: read-only, the same map and trajectory as when it was closed.
    reply = server.request("POST", "/api/sessions/f1/open");
    ASSERT_EQ(reply.status, 200) << reply.body;
    EXPECT_EQ(json::parse(reply.body)["state"], "opened");
    EXPECT_EQ(server.get("/api/sessions/f1/map.bt").body,
              readFile(fs::path(root) / "f1" / "map.bt"));
    EXPECT_EQ(server.get("/api/sessions/f1/trajectory.tum").body,
              readFile(fs::path(root) / "f1" / "trajectory.tum"));
    EXPECT_EQ(status(server, "f1")["poses"], f1["poses"]);

    // Merge: the second flight 20 m up, as a new read-only session.
    reply = server.request("POST", "/api/sessions/merge",
                           R"({"first": "f1", "second": "f2", "into": "both",
                               "transform": [0, 0, 20, 0, 0, 0, 1]})");
    ASSERT_EQ(reply.status, 200) << reply.body;
    const auto both = json::parse(reply.body);
    EXPECT_EQ(both["state"], "opened");
    EXPECT_EQ(both["frames"], 20);
    EXPECT_EQ(both["vehicles"], json({"sim-1", "sim-1-f2"}));
    EXPECT_GT(both["bounds"]["max"][2].get<double>(), f1["bounds"]["max"][2].get<double>() + 15);
    EXPECT_EQ(server.request("POST", "/api/sessions/merge", R"({"first": "f1"})").status, 400);
    EXPECT_EQ(server
                  .request("POST", "/api/sessions/merge",
                           R"({"first": "f1", "second": "f2", "into": "both"})")
                  .status,
              409);

    // Delete, and the offline tool refusing to write beside the running server.
    EXPECT_EQ(server.request("DELETE", "/api/sessions/f2").status, 200);
    EXPECT_FALSE(fs::exists(fs::path(root) / "f2"));
    EXPECT_EQ(server.request("DELETE", "/api/sessions/f2").status, 404);
    const auto refused = store(root, {"delete", "f1", "--yes"});
    EXPECT_EQ(refused.exit_code, 1);
    EXPECT_NE(refused.output.find("in use"), std::string::npos) << refused.output;
    const auto png =
        store(root, {"export", "both", "--format", "png", "--out", root + "/both.png"});
    EXPECT_EQ(png.exit_code, 0) << png.output;  // reading is fine beside a server
    EXPECT_EQ(readFile(root + "/both.png").substr(1, 3), "PNG");
  }

  // Offline: the catalog lists what the server left, check reads every journal.
  const auto listed = store(root, {"list", "--json"});
  ASSERT_EQ(listed.exit_code, 0) << listed.output;
  const auto rows = json::parse(listed.output);
  ASSERT_EQ(rows.size(), 2u);
  EXPECT_EQ(store(root, {"check"}).exit_code, 0);
  EXPECT_EQ(store(root, {"delete", "f1"}).exit_code, 1);  // no --yes
  EXPECT_EQ(store(root, {"close", "f1"}).exit_code, 1);   // already closed
  const auto merged = store(root, {"merge", "f1", "both", "--into", "all"});
  EXPECT_EQ(merged.exit_code, 0) << merged.output;
  EXPECT_EQ(store(root, {"delete", "f1", "--yes"}).exit_code, 0);
  const auto shown = store(root, {"show", "all"});
  ASSERT_EQ(shown.exit_code, 0) << shown.output;
  EXPECT_EQ(json::parse(shown.output.substr(shown.output.find('{')))["frames"], 32);

  // A restarted server keeps closed sessions in the store until asked for them.
  ServerProcess restarted(kDomain, {}, root);
  const auto list = json::parse(restarted.get("/api/sessions").body);
  ASSERT_EQ(list.size(), 2u);
  for (const auto& session : list) EXPECT_EQ(session["state"], "closed") << session;
  ASSERT_EQ(restarted.request("POST", "/api/sessions/all/open").status, 200);
  EXPECT_EQ(status(restarted, "all")["frames"], 32);
  restarted.process().stop();
  fs::remove_all(root);
}

// Samples refused because their session is closed or read-only, every topic (/metrics).
double refusedAsClosed(const ServerProcess& server) {
  const std::string text = server.get("/metrics").body;
  static const std::regex line(
      R"re(stereomap_samples_rejected_total\{topic="\w+",reason="(?:session_closed|read_only)"\} ([0-9.e+]+))re");
  double sum = 0;
  for (auto it = std::sregex_iterator(text.begin(), text.end(), line); it != std::sregex_iterator();
       ++it) {
    sum += std::stod((*it)[1]);
  }
  return sum;
}

size_t occurrences(const std::string& text, const std::string& what) {
  size_t count = 0;
  for (size_t at = text.find(what); at != std::string::npos; at = text.find(what, at + 1)) ++count;
  return count;
}

// Issue 54: a vehicle's counters reach the operator (the session's vehicle_status), and a
// vehicle still flying into a session the operator closed is answered: it says so once, sends
// nothing more (the server's count of refused samples stops growing), keeps what it holds in
// its spool (--on-closed keep, the default) and exits 3. A vehicle started on the closed
// session is told at once and, with --on-closed drop, gives up what it made.
TEST(SessionAdmin, AVehicleFlyingIntoAClosedSessionIsToldOnceAndStopsSending) {
  ServerProcess server(kDomain + 1);
  const std::string spool = server.store() + ".spool";
  const std::string log = server.store() + ".closed.log";
  ChildProcess onboard(onboardArgs(kDomain + 1, "closing", 200, {"--rate", "10", "--spool", spool}),
                       log);
  json seen;
  ASSERT_TRUE(waitUntil(30s, [&] {
    seen = status(server, "closing");
    return seen.is_object() && !seen["vehicle_status"].empty() &&
           seen["vehicle_status"][0]["frames"].get<int>() >= 20;
  })) << seen.dump();
  const json& counters = seen["vehicle_status"][0];
  EXPECT_EQ(counters["vehicle_id"], "sim-1");
  for (const char* key : {"skipped_frames", "late_frames", "spool_samples", "spool_bytes",
                          "given_up", "held_back", "received_s"}) {
    EXPECT_TRUE(counters.contains(key)) << key;
  }
  EXPECT_EQ(counters["given_up"], 0);
  EXPECT_FALSE(counters["session_closed"].get<bool>());
  EXPECT_NEAR(counters["received_s"].get<double>(), static_cast<double>(common::nowNs()) * 1e-9,
              3.0);

  ASSERT_EQ(server.request("POST", "/api/sessions/closing/close").status, 200);
  ASSERT_TRUE(waitUntil(10s, [&] {
    return readText(log).find("was closed by the server") != std::string::npos;
  })) << readText(log);
  // Told within a second or two: what it sent meanwhile was refused, and then nothing more.
  std::this_thread::sleep_for(2s);
  const double refused = refusedAsClosed(server);
  EXPECT_GT(refused, 0) << "the answer follows a refused sample";
  std::this_thread::sleep_for(4s);
  EXPECT_EQ(refusedAsClosed(server), refused) << "the vehicle still sends";
  const auto code = onboard.waitExit(60s);
  const std::string text = readText(log);
  EXPECT_EQ(code.value_or(-1), 3) << text;
  EXPECT_EQ(occurrences(text, "stops sending to it"), 1u) << text;
  EXPECT_NE(text.find("(--on-closed keep)"), std::string::npos) << text;
  const double kept = numberIn(text, R"(given up, (\d+) kept in the spool)");
  EXPECT_GT(kept, 50) << text;  // what it held and the frames it made after
  EXPECT_EQ(numberIn(text, R"((\d+) given up, \d+ kept)"), 0) << text;

  // Started on the closed session, with --on-closed drop.
  const std::string late_log = server.store() + ".late.log";
  ChildProcess late(onboardArgs(kDomain + 1, "closing", 30,
                                {"--rate", "10", "--spool", spool + "-late", "--vehicle", "uav-9",
                                 "--on-closed", "drop"}),
                    late_log);
  EXPECT_EQ(late.waitExit(60s).value_or(-1), 3) << readText(late_log);
  const std::string late_text = readText(late_log);
  EXPECT_EQ(occurrences(late_text, "stops sending to it"), 1u) << late_text;
  EXPECT_NE(late_text.find("(--on-closed drop)"), std::string::npos) << late_text;
  EXPECT_EQ(numberIn(late_text, R"(given up, (\d+) kept in the spool)"), 0) << late_text;
  EXPECT_EQ(status(server, "closing")["state"], "closed");
  EXPECT_EQ(server.process().stop(), 0);
}

}  // namespace
}  // namespace stereomap::testing
