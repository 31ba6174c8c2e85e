// Session management across real processes (issue 5): two sim flights stream to
// stereomap-server over DDS; the REST API closes, opens, merges and deletes sessions; then
// stereomap-store works on the same store offline, and refuses to write while a server
// holds it.
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <filesystem>
#include <fstream>

#include "tests/support/server_fixture.hpp"

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

}  // namespace
}  // namespace stereomap::testing
