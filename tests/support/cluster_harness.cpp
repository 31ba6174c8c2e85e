#include "tests/support/cluster_harness.hpp"

#include <filesystem>
#include <sstream>

#include "tests/support/stream_count.hpp"
#include "tests/support/websocket_client.hpp"

namespace stereomap::testing {

std::unique_ptr<ClusterHarness> ClusterHarness::start(std::string* why, int patroni_nodes) {
  auto harness = std::unique_ptr<ClusterHarness>(new ClusterHarness);
  if (patroni_nodes > 0) {
    harness->db_ = TestPatroni::start(patroni_nodes, why);
  } else {
    harness->db_ = TestPostgres::start(why);
  }
  if (!harness->db_) return nullptr;
  harness->dir_ = makeTempDir("stereomap-cluster");
  return harness;
}

ClusterHarness::~ClusterHarness() {
  vehicles_.clear();
  nginx_.reset();
  servers_.clear();
  db_.reset();
  std::error_code ec;
  std::filesystem::remove_all(dir_, ec);
}

ServerProcess& ClusterHarness::startServer(int domain, const std::string& id, double lease_s,
                                           const std::string& name,
                                           const std::vector<std::string>& extra_args) {
  std::ostringstream lease;
  lease << lease_s;
  auto& server = servers_[name.empty() ? id : name];
  std::vector<std::string> args{"--cluster", db_->url(), "--server-id", id, "--lease", lease.str()};
  args.insert(args.end(), extra_args.begin(), extra_args.end());
  server = std::make_unique<ServerProcess>(domain, args);
  return *server;
}

std::unique_ptr<ServerProcess> ClusterHarness::takeServer(const std::string& name) {
  auto it = servers_.find(name);
  if (it == servers_.end()) return nullptr;
  auto server = std::move(it->second);
  servers_.erase(it);
  return server;
}

bool ClusterHarness::startNginx(std::string* why) {
  std::vector<std::string> upstreams;
  for (const auto& [id, server] : servers_) {
    upstreams.push_back("127.0.0.1:" + std::to_string(server->port()));
  }
  nginx_ = TestNginx::start(upstreams, why);
  return nginx_ != nullptr;
}

void ClusterHarness::startVehicle(int domain, int i, int frames) {
  vehicles_.push_back(std::make_unique<ChildProcess>(
      userVehicleArgs(domain, "flight" + std::to_string(i), frames, "memory",
                      {"--vehicle", "v" + std::to_string(i), "--flush-timeout", "90",
                       "--trajectory-out", trajectoryOut(i)}),
      vehicleLog(i)));
}

std::string ClusterHarness::trajectoryOut(int i) const {
  return dir_ + "/trajectory" + std::to_string(i) + ".tum";
}

std::string ClusterHarness::vehicleLog(int i) const {
  return dir_ + "/vehicle" + std::to_string(i) + ".log";
}

bool ClusterHarness::waitForVehicles(std::chrono::seconds timeout, std::string* why) {
  for (size_t i = 0; i < vehicles_.size(); ++i) {
    if (vehicles_[i]->waitExit(timeout).value_or(-1) != 0) {
      if (why) *why = readText(vehicleLog(static_cast<int>(i)));
      return false;
    }
  }
  return true;
}

std::string ClusterHarness::query(const std::string& sql) { return db_->sql(sql).value_or(""); }

std::map<std::string, std::string> ClusterHarness::owners() {
  std::map<std::string, std::string> out;
  std::istringstream rows(query("SELECT id, coalesce(owner, '') FROM sm_sessions"));
  for (std::string line; std::getline(rows, line);) {
    const auto bar = line.find('|');
    if (bar != std::string::npos) out[line.substr(0, bar)] = line.substr(bar + 1);
  }
  return out;
}

bool ClusterHarness::allOwnedBy(const std::string& server) {
  const auto owned = owners();
  if (owned.empty()) return false;
  for (const auto& [session, owner] : owned) {
    if (owner != server) return false;
  }
  return true;
}

bool viewerSeesTiles(int port, const std::string& session, std::chrono::milliseconds timeout) {
  using Clock = std::chrono::steady_clock;
  const auto deadline = Clock::now() + timeout;
  WebSocketClient ws(port, "/ws?session=" + session);
  if (ws.status() != 101) return false;
  ws.sendText(R"({"type":"hello","protocol":2})");
  ws.sendText(R"({"type":"subscribe","session":")" + session + R"("})");
  if (ws.readUntil("\"subscribed\"", timeout).kind != WsMessage::Kind::kText) return false;
  ws.sendText(R"({"type":"view","id":1,"eye":[0,0,30]})");
  while (Clock::now() < deadline) {
    const auto message =
        ws.read(std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()));
    if (message.kind == WsMessage::Kind::kBinary) return true;
    if (message.kind == WsMessage::Kind::kClose || message.kind == WsMessage::Kind::kNone) {
      return false;
    }
  }
  return false;
}

}  // namespace stereomap::testing
