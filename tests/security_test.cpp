// Security holes found from outside (issue 13), tried against a real stereomap-server:
// files outside the viewer's folder through any spelling of a path, the token in the process
// list, and ids that used to reach the file system (and abort the server) on every route.
#include <gtest/gtest.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>

#include "tests/support/server_fixture.hpp"

namespace stereomap::testing {
namespace {

using namespace std::chrono_literals;
namespace fs = std::filesystem;

constexpr int kDomain = 76;
const std::string kToken = "s3cret-Token-4711";

std::string readFile(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

// A viewer folder with files, a dot file, and links that leave the folder.
fs::path makeWebRoot() {
  fs::path root = makeTempDir("stereomap-web");
  fs::create_directories(root / "assets");
  std::ofstream(root / "index.html") << "<html>viewer index</html>";
  std::ofstream(root / "assets" / "app.js") << "console.log('viewer app');";
  std::ofstream(root / ".secret") << "dot file";
  fs::create_symlink("/etc/passwd", root / "leak.txt");
  fs::create_directory_symlink("/etc", root / "etc");
  fs::create_symlink("assets/app.js", root / "alias.js");  // a link that stays inside
  // Dangling links (one used to end the scan, leaving the viewer without its files).
  for (const char* name : {"a-broken.js", "m-broken.js", "z-broken.js", "assets/broken.css"}) {
    fs::create_symlink("/nonexistent/file", root / name);
  }
  return root;
}

// Every spelling of "a file outside the viewer" the issue lists, and more of their kind.
const std::vector<std::string> kOutsidePaths = {
    "//proc/self/cmdline",
    "//proc/self/environ",
    "//etc/passwd",
    "///etc/passwd",
    "/.//etc/passwd",
    "/%2F%2Fetc/passwd",
    "/%2fetc%2fpasswd",
    "/%2Fproc%2Fself%2Fcmdline",
    "/..%2f..%2f..%2fetc/passwd",
    "/%2e%2e/%2e%2e/etc/passwd",
    "/.%2e/.%2e/etc/passwd",
    "/./../../../etc/passwd",
    "/assets/../../../../etc/passwd",
    "/assets%2f..%2f..%2f..%2fetc%2fpasswd",
    "/leak.txt",
    "/etc/passwd",
    "/etc/hostname",
    "/.secret",
    "/index.html%00.js",
    "/%00",
    "/assets/app.js/../../../etc/passwd",
    "//%65tc/passwd",
    "/\\etc\\passwd",
};

TEST(Security, OnlyTheViewersOwnFilesAreServedWhateverThePath) {
  const fs::path web = makeWebRoot();
  const fs::path token_file = web.string() + ".token";
  std::ofstream(token_file) << kToken << "\n";
  ServerProcess server(kDomain, {"--web-root", web.string(), "--token-file", token_file.string()});

  // The token is not in the process list.
  const std::string cmdline =
      readFile("/proc/" + std::to_string(server.process().pid()) + "/cmdline");
  EXPECT_EQ(cmdline.find(kToken), std::string::npos);
  EXPECT_EQ(server.get("/api/sessions").status, 401);
  EXPECT_EQ(
      server.request("GET", "/api/sessions", "", "Authorization: Bearer " + kToken + "\r\n").status,
      200);
  // ?token= is read as a query parameter: whole names only, percent escapes decoded.
  EXPECT_EQ(server.get("/api/sessions?xtoken=" + kToken).status, 401);
  EXPECT_EQ(server.get("/api/sessions?xtoken=no&token=" + kToken).status, 200);
  EXPECT_EQ(server.get("/api/sessions?token=s3cret%2DToken%2D4711").status, 200);

  const std::string store_file = "//" + server.store().substr(1) + "/catalog.sqlite";
  std::vector<std::string> paths = kOutsidePaths;
  paths.push_back(store_file);
  paths.push_back("/" + server.store() + "/store.lock");
  for (const auto& path : paths) {
    for (const std::string& headers : {std::string(), "Authorization: Bearer " + kToken + "\r\n"}) {
      SCOPED_TRACE(path + (headers.empty() ? " without the token" : " with the token"));
      const auto reply = server.request("GET", path, "", headers);
      EXPECT_NE(reply.status, 0) << "no answer";
      EXPECT_NE(reply.status, 200) << reply.body;
      EXPECT_EQ(reply.body.find("root:"), std::string::npos);
      EXPECT_EQ(reply.body.find(kToken), std::string::npos);
      EXPECT_EQ(reply.body.find("stereomap-server"), std::string::npos);
      EXPECT_EQ(reply.body.find("SQLite"), std::string::npos);
      EXPECT_EQ(reply.body.find("dot file"), std::string::npos);
    }
  }
  // What the viewer needs is still there, by any spelling of its own names.
  for (const auto& [path, expected] :
       std::vector<std::pair<std::string, std::string>>{{"/", "viewer index"},
                                                        {"/index.html", "viewer index"},
                                                        {"/?token=x#y", "viewer index"},
                                                        {"/assets/app.js", "viewer app"},
                                                        {"/assets/app.js?v=3", "viewer app"},
                                                        {"/%61ssets/app%2Ejs", "viewer app"},
                                                        {"/alias.js", "viewer app"}}) {
    SCOPED_TRACE(path);
    const auto reply = server.get(path);
    EXPECT_EQ(reply.status, 200);
    EXPECT_NE(reply.body.find(expected), std::string::npos) << reply.body;
  }
  EXPECT_TRUE(server.process().running());
  fs::remove_all(web);
  fs::remove(token_file);
}

TEST(Security, EveryRouteRefusesBadIdsAndTheServerLivesOn) {
  ::setenv("STEREOMAP_TOKEN", kToken.c_str(), 1);  // the token from the environment
  ServerProcess server(79);  // a domain of its own: ctest runs its neighbours side by side
  ::unsetenv("STEREOMAP_TOKEN");
  EXPECT_EQ(readFile("/proc/" + std::to_string(server.process().pid()) + "/cmdline").find(kToken),
            std::string::npos);
  const std::string auth = "Authorization: Bearer " + kToken + "\r\n";
  EXPECT_EQ(server.get("/api/sessions").status, 401);

  const std::vector<std::string> ids = {std::string(256, 'a'),
                                        std::string(300, 'x'),
                                        std::string(4000, 'b'),
                                        "..",
                                        "%2e%2e",
                                        "a%2Fb",
                                        "%00",
                                        "a%20b",
                                        "\xff\xfe",
                                        "*"};
  for (const auto& id : ids) {
    const std::vector<std::pair<std::string, std::string>> requests = {
        {"GET", "/api/sessions/" + id},
        {"GET", "/api/sessions/" + id + "/map.bt"},
        {"GET", "/api/sessions/" + id + "/map.ot"},
        {"GET", "/api/sessions/" + id + "/map.ply"},
        {"GET", "/api/sessions/" + id + "/map.png?zmin=0&zmax=1"},
        {"GET", "/api/sessions/" + id + "/trajectory.tum"},
        {"HEAD", "/api/sessions/" + id + "/map.bt"},
        {"POST", "/api/sessions/" + id + "/open"},
        {"POST", "/api/sessions/" + id + "/close"},
        {"DELETE", "/api/sessions/" + id}};
    for (const auto& [method, path] : requests) {
      SCOPED_TRACE(method + " " + path.substr(0, 60));
      const auto reply = server.request(method, path, "", auth);
      EXPECT_EQ(reply.status, 400) << reply.body;
      ASSERT_TRUE(server.process().running()) << server.log();
    }
    for (const std::string& body : {R"({"first": ")" + id + R"(", "second": "b", "into": "c"})",
                                    R"({"first": "a", "second": ")" + id + R"(", "into": "c"})",
                                    R"({"first": "a", "second": "b", "into": ")" + id + R"("})"}) {
      SCOPED_TRACE("merge " + body.substr(0, 60));
      const auto reply = server.request("POST", "/api/sessions/merge", body, auth);
      EXPECT_EQ(reply.status, 400) << reply.body;
      ASSERT_TRUE(server.process().running()) << server.log();
    }
  }
  const auto vehicle = server.request(
      "GET", "/api/sessions/s1/trajectory.tum?vehicle=" + std::string(256, 'v'), "", auth);
  EXPECT_EQ(vehicle.status, 400) << vehicle.body;
  EXPECT_EQ(server.get("/healthz").status, 200);
  EXPECT_TRUE(server.process().running());
  EXPECT_EQ(server.log().find("terminate"), std::string::npos) << server.log();
}

TEST(Security, TokenFlagsAreCheckedAtStartUp) {
  const std::string server = std::string(STEREOMAP_BIN_DIR) + "/stereomap-server";
  auto run =
      runTool({server, "--token", "a", "--token-file", "/nonexistent", "--domain", "79"}, 30s);
  EXPECT_EQ(run.exit_code, 2) << run.output;
  run = runTool({server, "--token-file", "/nonexistent/token", "--domain", "79"}, 30s);
  EXPECT_EQ(run.exit_code, 2) << run.output;
  EXPECT_NE(run.output.find("/nonexistent/token"), std::string::npos) << run.output;
  // Off loopback: https, or plain HTTP only when asked for (and never without a token).
  run = runTool({server, "--http", "0.0.0.0:0", "--token", "a", "--domain", "79"}, 30s);
  EXPECT_EQ(run.exit_code, 2) << run.output;
  EXPECT_NE(run.output.find("--insecure-http"), std::string::npos) << run.output;
  run = runTool({server, "--http", "127.0.0.1:0", "--tls-cert", "/etc/hostname", "--domain", "79"},
                30s);
  EXPECT_EQ(run.exit_code, 2) << run.output;
  run = runTool({server, "--http", "0.0.0.0:0", "--insecure-http", "--domain", "79"}, 30s);
  EXPECT_EQ(run.exit_code, 2) << run.output;
  EXPECT_NE(run.output.find("give tokens"), std::string::npos) << run.output;
  run = runTool({server, "--help"}, 30s);
  EXPECT_EQ(run.exit_code, 0);
  EXPECT_NE(run.output.find("--token-file"), std::string::npos);
  EXPECT_NE(run.output.find("STEREOMAP_TOKEN"), std::string::npos);
}

// Two roles (issue 55): tokens made by stereomap-certs, kept hashed; a viewer reads, an
// operator changes, two viewers' tokens at once (a rotation), and every change is logged with
// the token's name.
TEST(Security, ViewersReadOperatorsChangeAndEveryChangeIsLogged) {
  const std::string dir = makeTempDir("stereomap-tokens");
  const std::string tokens = dir + "/tokens";
  const auto make = [&](const std::string& role, const std::string& name) {
    const auto run =
        runTool({std::string(STEREOMAP_BIN_DIR) + "/stereomap-certs", "token", tokens, role, name});
    EXPECT_EQ(run.exit_code, 0) << run.output;
    return run.output.substr(0, run.output.find('\n'));
  };
  const std::string alice = make("operator", "alice");
  const std::string wall = make("viewer", "wall");
  const std::string wall_new = make("viewer", "wall-new");
  ASSERT_EQ(wall.size(), 48u);
  for (const auto& token : {alice, wall, wall_new}) {
    EXPECT_EQ(readFile(tokens).find(token), std::string::npos) << "kept in clear";
  }
  ServerProcess server(130, {"--tokens", tokens});
  ChildProcess vehicle(onboardArgs(130, "roles", 10), server.logPath() + ".vehicle");
  ASSERT_EQ(vehicle.waitExit(scaledTimeout(60s)).value_or(-1), 0);
  const auto as = [](const std::string& token) {
    return "Authorization: Bearer " + token + "\r\n";
  };
  EXPECT_EQ(server.get("/api/sessions").status, 401);
  EXPECT_EQ(server.request("GET", "/api/sessions", "", as("guess")).status, 401);
  EXPECT_EQ(server.request("POST", "/api/sessions/roles/close").status, 401);
  for (const auto& token : {wall, wall_new}) {
    EXPECT_EQ(server.request("GET", "/api/sessions", "", as(token)).status, 200);
    EXPECT_EQ(server.get("/api/sessions/roles/trajectory.tum?token=" + token).status, 200);
    for (const auto& [method, path] : {std::pair{"POST", "/api/sessions/roles/close"},
                                       {"DELETE", "/api/sessions/roles"},
                                       {"POST", "/api/sessions/merge"}}) {
      const auto reply = server.request(method, path, R"({"first": "roles", "second": "roles",
          "into": "x"})",
                                        as(token));
      EXPECT_EQ(reply.status, 403) << method << " " << path << ": " << reply.body;
    }
  }
  EXPECT_NE(server.log().find("the token 'wall' is a viewer's"), std::string::npos);
  EXPECT_EQ(server.request("GET", "/api/sessions/roles", "", as(wall)).status, 200)
      << "a viewer's refused write touched nothing";
  const auto closed = server.request("POST", "/api/sessions/roles/close", "", as(alice));
  EXPECT_EQ(closed.status, 200) << closed.body;
  EXPECT_NE(server.log().find("POST /api/sessions/roles/close by 'alice' (operator)"),
            std::string::npos)
      << server.log();
  fs::remove_all(dir);
}

}  // namespace
}  // namespace stereomap::testing
