#include "tests/support/patroni.hpp"

#include <signal.h>

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <thread>

namespace stereomap::testing {

namespace fs = std::filesystem;
using namespace std::chrono_literals;

std::unique_ptr<TestPatroni> TestPatroni::start(int nodes, std::string* why) {
  auto fail = [&](const std::string& reason) -> std::unique_ptr<TestPatroni> {
    if (why) *why = reason;
    return nullptr;
  };
  for (const char* binary : {"/usr/bin/patroni", "/usr/bin/etcd"}) {
    if (!fs::exists(binary)) {
      return fail(std::string(binary) +
                  " is not installed (scripts/install-deps: patroni, etcd-server)");
    }
  }
  auto db = std::unique_ptr<TestPatroni>(new TestPatroni);
  db->bin_ = postgresBinDir();
  if (db->bin_.empty()) return fail("PostgreSQL is not installed");
  db->dir_ = makeTempDir("stereomap-patroni");
  if (!handToUnprivileged(db->dir_)) return fail("cannot hand " + db->dir_ + " to nobody");
  db->password_ = randomPassword();
  db->scope_ = "stereomap-test";
  db->etcd_port_ = unusedPort();
  db->etcd_peer_port_ = unusedPort();
  const std::string client = "http://127.0.0.1:" + std::to_string(db->etcd_port_);
  const std::string peer = "http://127.0.0.1:" + std::to_string(db->etcd_peer_port_);
  db->etcd_ = std::make_unique<ChildProcess>(
      asUnprivileged({"/usr/bin/etcd", "--enable-v2", "--name", "e0", "--data-dir",
                      db->dir_ + "/etcd", "--listen-client-urls", client, "--advertise-client-urls",
                      client, "--listen-peer-urls", peer, "--initial-advertise-peer-urls", peer,
                      "--initial-cluster", "e0=" + peer}),
      db->dir_ + "/etcd.log");
  if (!waitUntil(20s, [&] { return httpGet(db->etcd_port_, "/health").status == 200; })) {
    return fail("etcd did not start: " + logTail(db->dir_ + "/etcd.log"));
  }
  for (int i = 0; i < std::max(2, nodes); ++i) {
    Node node;
    node.name = "pg" + std::to_string(i);
    node.data = db->dir_ + "/" + node.name;
    node.pg_port = unusedPort();
    node.rest_port = unusedPort();
    db->nodes_.push_back(std::move(node));
  }
  // The first bootstraps the cluster; the others are made from it by base backups.
  if (!db->startNode(db->nodes_[0], why)) return nullptr;
  if (!waitUntil(
          60s, [&] { return db->primary() == 0; }, 200ms)) {
    return fail("the first node did not become the primary: " + logTail(db->dir_ + "/pg0.log"));
  }
  for (size_t i = 1; i < db->nodes_.size(); ++i) {
    if (!db->startNode(db->nodes_[i], why)) return nullptr;
  }
  if (!db->restart(why)) return nullptr;
  return db;
}

bool TestPatroni::startNode(Node& node, std::string* why) {
  std::ifstream in(STEREOMAP_PATRONI_TEMPLATE);
  std::stringstream text;
  text << in.rdbuf();
  if (text.str().empty()) {
    if (why) *why = std::string("cannot read ") + STEREOMAP_PATRONI_TEMPLATE;
    return false;
  }
  std::string config = text.str();
  const std::pair<std::string, std::string> values[] = {
      {"@SCOPE@", scope_},
      {"@NAME@", node.name},
      {"@REST@", "127.0.0.1:" + std::to_string(node.rest_port)},
      {"@REST_LISTEN@", "127.0.0.1:" + std::to_string(node.rest_port)},
      {"@ETCD@", "127.0.0.1:" + std::to_string(etcd_port_)},
      {"@NETWORK@", "127.0.0.1/32"},
      {"@LISTEN@", "127.0.0.1:" + std::to_string(node.pg_port)},
      {"@PG@", "127.0.0.1:" + std::to_string(node.pg_port)},
      {"@DATA@", node.data},
      {"@BIN@", bin_},
      {"@PGPASS@", dir_ + "/" + node.name + ".pgpass"},
      {"@PASSWORD@", password_},
      {"@REPLICATION_PASSWORD@", password_},
      {"@SOCKETS@", dir_},
  };
  for (const auto& [from, to] : values) config = replaced(config, from, to);
  const std::string file = dir_ + "/" + node.name + ".yml";
  std::ofstream(file) << config;
  node.patroni = std::make_unique<ChildProcess>(
      asUnprivileged({"/usr/bin/env", "HOME=" + dir_, "/usr/bin/patroni", file}),
      dir_ + "/" + node.name + ".log");
  return true;
}

TestPatroni::~TestPatroni() {
  resume();
  // Patroni stops its PostgreSQL when it is stopped (SIGTERM); what is left is killed.
  for (auto& node : nodes_) {
    if (node.patroni) node.patroni->stop(std::chrono::seconds(20));
    if (const pid_t pid = postmasterOf(node); pid > 0) killWithChildren(pid);
  }
  if (etcd_) etcd_->stop();
  std::error_code ec;
  fs::remove_all(dir_, ec);
}

std::string TestPatroni::url(const std::string& database) const {
  std::string hosts;
  for (const auto& node : nodes_) {
    hosts += (hosts.empty() ? "" : ",") + std::string("127.0.0.1:") + std::to_string(node.pg_port);
  }
  return "postgresql://stereomap:" + password_ + "@" + hosts + "/" + database +
         "?target_session_attrs=read-write";
}

std::optional<std::string> TestPatroni::sql(const std::string& statement,
                                            const std::string& database) {
  return runPsql(bin_, url(database) + "&connect_timeout=3", statement);
}

std::optional<int> TestPatroni::primary() {
  for (const auto& node : nodes_) {
    const auto reply = httpGet(node.rest_port, "/cluster");
    if (reply.status != 200) continue;
    const auto cluster = nlohmann::json::parse(reply.body, nullptr, /*allow_exceptions=*/false);
    if (!cluster.is_object() || !cluster.contains("members")) continue;
    for (const auto& member : cluster["members"]) {
      if (member.value("role", "") != "leader" || member.value("state", "") != "running") continue;
      for (size_t i = 0; i < nodes_.size(); ++i) {
        if (member.value("port", 0) == nodes_[i].pg_port) return static_cast<int>(i);
      }
    }
    return std::nullopt;
  }
  return std::nullopt;
}

bool TestPatroni::healthy() {
  const auto leader = primary();
  if (!leader) return false;
  const auto reply = httpGet(nodes_[static_cast<size_t>(*leader)].rest_port, "/cluster");
  const auto cluster = nlohmann::json::parse(reply.body, nullptr, false);
  if (!cluster.is_object() || !cluster.contains("members")) return false;
  size_t streaming = 0, synchronous = 0;
  for (const auto& member : cluster["members"]) {
    const std::string role = member.value("role", "");
    if (role == "leader") continue;
    // Patroni 3.0 says "running" for a standby that streams.
    const std::string state = member.value("state", "");
    if (state != "running" && state != "streaming") return false;
    if (!member.contains("lag") || !member["lag"].is_number()) return false;
    ++streaming;
    synchronous += role == "sync_standby";
  }
  return streaming + 1 == nodes_.size() && synchronous >= 1;
}

bool TestPatroni::restart(std::string* why) {
  if (waitUntil(
          120s, [&] { return healthy(); }, 200ms))
    return true;
  if (why) {
    *why = "the database did not come back whole (every node streaming from a primary):";
    for (const auto& node : nodes_) {
      *why += "\n--- " + node.name + ":\n" + logTail(dir_ + "/" + node.name + ".log");
    }
  }
  return false;
}

pid_t TestPatroni::postmasterOf(const Node& node) const {
  std::ifstream in(node.data + "/postmaster.pid");
  long pid = 0;
  if (!(in >> pid) || pid <= 0) return 0;
  return ::kill(static_cast<pid_t>(pid), 0) == 0 ? static_cast<pid_t>(pid) : 0;
}

void TestPatroni::crash() {
  const auto leader = primary();
  if (!leader) return;
  if (const pid_t pid = postmasterOf(nodes_[static_cast<size_t>(*leader)]); pid > 0) {
    killWithChildren(pid);
  }
}

void TestPatroni::pause() {
  const auto leader = primary();
  if (!leader || paused_ != 0) return;
  paused_ = postmasterOf(nodes_[static_cast<size_t>(*leader)]);
  if (paused_ > 0) signalWithChildren(paused_, SIGSTOP);
}

void TestPatroni::resume() {
  if (paused_ > 0) signalWithChildren(paused_, SIGCONT);
  paused_ = 0;
}

}  // namespace stereomap::testing
