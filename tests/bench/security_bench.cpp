// stereomap-bench-security (issue 55): what a secured deployment refuses and what it costs,
// with real processes, each measurement side by side with the same deployment left open.
//   1. Attacks (the issue's item 6, each tried at least once) against a deployment made by
//      stereomap-certs: refused or not, each named on stderr.
//   2. One vehicle's cost: the same sim flight, as the thinned stream and as whole clouds, open
//      and secured, alternating, --runs times: the bytes on the loopback (tcpdump, the domain's
//      ports), the vehicle's CPU (/usr/bin/time), the server's CPU (/proc), samples/s.
//   3. The fleet: N vehicles' recorded streams (tests/bench/fleet.hpp) over DDS into one server,
//      open and secured: the worst session's publish lag p95 and the server's CPU.
//   4. TLS: a fresh browser's first view over https against plain http
//      (tests/interop/tls_clients.mjs --measure).
// Ends with exactly:
//   security: <V> vehicles authenticated, <A>/<T> attacks refused; link +<B>%, vehicle CPU
//   +<C>%, server CPU +<S>%; fleet of <N> secured: lag p95 <L> ms; tls first view <W> ms
//   stereomap-bench-security [--vehicles N] [--fleet-seconds S] [--frames F] [--runs R]
//                            [--streams K] [--record-dir DIR] [--tls-rounds N]
#include <spdlog/spdlog.h>
#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include <unistd.h>
#include <algorithm>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <regex>
#include <sstream>
#include <thread>

#include "common/cli.hpp"
#include "tests/bench/fleet.hpp"
#include "tests/support/cluster_harness.hpp"
#include "tests/support/secure_deployment.hpp"
#include "tests/support/server_fixture.hpp"
#include "tests/support/stream_count.hpp"

namespace {

using namespace stereomap;
using namespace stereomap::testing;
using namespace std::chrono_literals;
namespace fs = std::filesystem;
using json = nlohmann::json;

const std::string kBin = STEREOMAP_BIN_DIR;
// 140-146 attacks, 147 one vehicle's cost, 148-149 the fleet, 150-151 TLS, 152 recordings.
constexpr int kAttackDomain = 140;
constexpr int kCostDomain = 147;
constexpr int kFleetDomain = 148;
constexpr int kTlsDomain = 150;
constexpr int kRecordDomain = 152;

bool has(const std::vector<std::string>& ids, const std::string& id) {
  return std::find(ids.begin(), ids.end(), id) != ids.end();
}

// user + system seconds of a running process (/proc/PID/stat fields 14 and 15).
double processCpuSeconds(pid_t pid) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/stat");
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const size_t close = text.rfind(')');
  if (close == std::string::npos) return 0;
  std::istringstream fields(text.substr(close + 2));
  std::string field;
  double ticks = 0;
  for (int i = 3; i <= 15 && fields >> field; ++i) {
    if (i >= 14) ticks += std::stod(field);
  }
  return ticks / static_cast<double>(::sysconf(_SC_CLK_TCK));
}

// The bytes of every packet in a pcap file (their lengths on the wire).
uint64_t pcapBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  char header[24];
  if (!in.read(header, sizeof header)) return 0;
  uint64_t total = 0;
  char record[16];
  while (in.read(record, sizeof record)) {
    uint32_t captured = 0, original = 0;
    std::memcpy(&captured, record + 8, 4);
    std::memcpy(&original, record + 12, 4);
    total += original;
    in.seekg(captured, std::ios::cur);
  }
  return total;
}

// Cyclone's ports of a domain (7400 + 250 d, and the 250 after: discovery and data).
std::string domainPorts(int domain) {
  const int base = 7400 + 250 * domain;
  return "udp portrange " + std::to_string(base) + "-" + std::to_string(base + 249);
}

// ---- 1. attacks --------------------------------------------------------------------------

struct Attacks {
  int tried = 0, refused = 0;
  void add(const std::string& what, bool was_refused) {
    ++tried;
    refused += was_refused ? 1 : 0;
    std::fprintf(stderr, "attack %2d %s: %s\n", tried, was_refused ? "refused" : "NOT REFUSED",
                 what.c_str());
  }
};

void attacks(const Deployment& d, Attacks& a) {
  {
    ServerProcess server(kAttackDomain, {"--security", d.server()});
    ChildProcess listener(
        {kBin + "/stereomap-dds-probe", "read", "--partition", "sm/*", "--seconds", "10",
         "--domain", std::to_string(kAttackDomain), "--dds-config", STEREOMAP_DDS_CONFIG},
        server.logPath() + ".listener");
    ChildProcess flood(
        {"/bin/sh", "-c",
         "CYCLONEDDS_URI=file://" + std::string(STEREOMAP_DDS_CONFIG) + " exec ddsperf -i " +
             std::to_string(kAttackDomain) + " -D 8 pub 500Hz size 4k"},
        server.logPath() + ".ddsperf");
    const auto good = fly(kAttackDomain, "good", "v1", d.vehicle("v1"));
    (void)flood.waitExit(30s);
    (void)listener.waitExit(60s);
    const auto open = fly(kAttackDomain, "open", "v1", "");
    const auto ids = sessionIds(server);
    const std::string metrics = server.get("/metrics").body;
    const bool untouched = ids == std::vector<std::string>{"good"} &&
                           unacknowledged(good.log) == 0 &&
                           metrics.find("stereomap_samples_rejected_total{") == std::string::npos;
    a.add("our vehicle binary without certificates publishes a session",
          unacknowledged(open.log) > 0 && !has(ids, "open") && untouched);
    a.add("ddsperf without certificates floods the secured domain while a vehicle flies",
          flood.waitExit(1s).value_or(-1) == 0 && untouched);
    a.add("a reader without certificates reads every partition during a flight",
          readText(server.logPath() + ".listener").find("read: read 0, matched 0") !=
              std::string::npos);
  }
  {
    const int domain = kAttackDomain + 1;
    ServerProcess server(domain, {"--security", d.server()});
    const auto as_v2 = fly(domain, "as", "v2", d.vehicle("v1"), 5);
    a.add("vehicle v1 flies as v2", as_v2.exit_code != 0);
    a.add("v1 writes into v2's partition",
          probe({"write", "--partition", "sm/as/v/v2", "--vehicle", "v2", "--session", "as"},
                domain, d.vehicle("v1"))
                  .find("write: refused") != std::string::npos);
    (void)probe({"write", "--partition", "sm/as/v/v1", "--vehicle", "v2", "--session", "as",
                 "--count", "10"},
                domain, d.vehicle("v1"));
    const bool counted = waitUntil(10s, [&] {
      return seriesValue(server.get("/metrics").body,
                         "stereomap_samples_rejected_total{topic=\"Pose\",reason=\"identity\"}") >=
             10;
    });
    a.add("v1 writes samples as v2 in its own partition",
          counted && !has(sessionIds(server), "as") &&
              server.log().find("CN=v1") != std::string::npos);
    a.add("v1 reads v2's acknowledgements",
          probe({"read", "--topic", "ack", "--partition", "sm/as/v/v2", "--seconds", "1"}, domain,
                d.vehicle("v1"))
                  .find("read: refused") != std::string::npos);
  }
  {
    const int domain = kAttackDomain + 2;
    const std::string log = makeTempDir("stereomap-bench-ack") + "/onboard.log";
    ChildProcess vehicle(
        onboardArgs(domain, "acked", 60,
                    {"--vehicle", "v1", "--rate", "5", "--security", d.vehicle("v1")}),
        log);
    const auto forge = [&](const std::string& identity) {
      return probe({"write", "--topic", "ack", "--partition", "sm/acked/v/v1", "--vehicle", "v1",
                    "--session", "acked", "--match-wait", "8", "--count", "20"},
                   domain, identity);
    };
    a.add("a participant without certificates acknowledges v1's samples",
          forge("").find("write: wrote 20, matched 0") != std::string::npos);
    a.add("vehicle v2 acknowledges v1's samples",
          forge(d.vehicle("v2")).find("write: refused") != std::string::npos);
    vehicle.stop();
    fs::remove_all(fs::path(log).parent_path());
  }
  {
    const int domain = kAttackDomain + 3;
    ServerProcess server(domain, {"--security", d.server()});
    a.add("a vehicle whose certificate expired flies",
          fly(domain, "old", "old", d.vehicle("old"), 5).exit_code != 0 &&
              !has(sessionIds(server), "old"));
    const auto lost = fly(domain, "lost", "lost", d.vehicle("lost"));
    a.add("a vehicle whose certificate was revoked flies",
          unacknowledged(lost.log) > 0 && !has(sessionIds(server), "lost"));
  }
  {
    const std::string dir = makeTempDir("stereomap-bench-capture");
    ChildProcess capture({"/usr/bin/tcpdump", "-i", "lo", "-U", "-w", dir + "/lo.pcap", "udp"},
                         dir + "/tcpdump.log");
    waitUntil(10s, [&] { return fs::exists(dir + "/lo.pcap"); });
    std::this_thread::sleep_for(500ms);
    {
      ServerProcess secured(kAttackDomain + 4, {"--security", d.server()});
      ServerProcess open(kAttackDomain + 5);
      (void)fly(kAttackDomain + 4, "secret-flight-4711", "v1", d.vehicle("v1"));
      (void)fly(kAttackDomain + 5, "open-flight-4711", "v1", "");
    }
    capture.stop();
    const std::string wire = readText(dir + "/lo.pcap");
    a.add("a capture of the loopback shows a secured flight's session id",
          wire.find("open-flight-4711") != std::string::npos &&
              wire.find("secret-flight-4711") == std::string::npos);
    fs::remove_all(dir);
  }
  {
    const std::string tokens = d.dir + "/tokens";
    const auto made = runTool({kBin + "/stereomap-certs", "token", tokens, "viewer", "wall"});
    const std::string token = made.output.substr(0, made.output.find('\n'));
    const std::string auth = "Authorization: Bearer " + token + "\r\n";
    ServerProcess server(kAttackDomain + 6, {"--tokens", tokens});
    (void)fly(kAttackDomain + 6, "kept", "v1", "", 5);
    const auto deleted = server.request("DELETE", "/api/sessions/kept", "", auth);
    a.add("a viewer's token deletes a session",
          deleted.status == 403 &&
              server.request("GET", "/api/sessions/kept", "", auth).status == 200);
    std::string why;
    auto cluster = ClusterHarness::start(&why);
    bool refused = false;
    if (cluster) {
      cluster->startServer(kAttackDomain + 6, "a", 2, "", {"--tokens", tokens});
      if (cluster->startNginx(&why)) {
        cluster->startVehicle(kAttackDomain + 6, 0, 30);
        const int proxy = cluster->nginx().port();
        std::string url;
        waitUntil(60s, [&] {
          const auto index = httpRequest(proxy, "GET", "/api/sessions/flight0/tiles", "", auth);
          if (index.status != 200) return false;
          const auto listed = json::parse(index.body);
          if (listed["tiles"].empty()) return false;
          url = listed["tiles"][0]["url"];
          return true;
        });
        cluster->waitForVehicles(60s, &why);
        const auto listed =
            json::parse(httpRequest(proxy, "GET", "/api/sessions/flight0/tiles", "", auth).body);
        if (!listed["tiles"].empty()) url = listed["tiles"][0]["url"];
        for (int i = 0; i < 2; ++i) (void)httpRequest(proxy, "GET", url, "", auth);
        const bool cached =
            httpRequest(proxy, "GET", url, "", auth).header("X-Cache-Status") == "HIT";
        refused = cached && httpGet(proxy, url).status == 401;
      }
    }
    a.add("a tokenless client asks nginx for a tile a viewer just fetched" +
              (cluster ? std::string() : " (no cluster: " + why + ")"),
          refused);
  }
}

// ---- 2. one vehicle's cost ---------------------------------------------------------------

struct Cost {
  uint64_t link_bytes = 0;
  double vehicle_cpu_s = 0, server_cpu_s = 0, seconds = 0;
  uint64_t samples = 0;
};

Cost flightCost(const Deployment& d, bool secured, bool whole, int frames) {
  Cost cost;
  const std::string dir = makeTempDir("stereomap-bench-cost");
  std::vector<std::string> server_args;
  if (secured) server_args = {"--security", d.server()};
  ServerProcess server(kCostDomain, server_args);
  ChildProcess capture(
      {"/usr/bin/tcpdump", "-i", "lo", "-U", "-w", dir + "/lo.pcap", domainPorts(kCostDomain)},
      dir + "/tcpdump.log");
  waitUntil(10s, [&] { return fs::exists(dir + "/lo.pcap"); });
  std::this_thread::sleep_for(300ms);
  std::vector<std::string> flags = {"--vehicle", "v1", "--rate", "10", "--seed", "3"};
  if (secured) flags.insert(flags.end(), {"--security", d.vehicle("v1")});
  if (!whole) {  // the vehicle's own link defaults (onboardArgs sends whole clouds otherwise)
    flags.insert(flags.end(),
                 {"--min-new", "0.1", "--map-resolution", "0.1", "--link-budget", "1Mbit"});
  }
  auto argv = onboardArgs(kCostDomain, "cost", frames, flags);
  argv.insert(argv.begin(), {"/usr/bin/time", "-o", dir + "/time", "-f", "%U %S"});
  const double server_before = processCpuSeconds(server.process().pid());
  const auto start = std::chrono::steady_clock::now();
  ChildProcess vehicle(argv, dir + "/onboard.log");
  (void)vehicle.waitExit(300s);
  cost.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::this_thread::sleep_for(500ms);
  cost.server_cpu_s = processCpuSeconds(server.process().pid()) - server_before;
  capture.stop();
  cost.link_bytes = pcapBytes(dir + "/lo.pcap");
  std::ifstream time(dir + "/time");
  double user = 0, system = 0;
  time >> user >> system;
  cost.vehicle_cpu_s = user + system;
  const auto session = json::parse(server.get("/api/sessions/cost").body, nullptr, false);
  if (session.is_object()) {
    cost.samples = session.value("poses", uint64_t{0}) + session.value("frames", uint64_t{0});
  }
  fs::remove_all(dir);
  return cost;
}

double percentMore(double secured, double open) {
  return open > 0 ? 100.0 * (secured - open) / open : 0;
}

// ---- 3. the fleet ------------------------------------------------------------------------

struct FleetCost {
  int sessions = 0;  // sessions the server took with every vehicle's samples
  double lag_p95_ms = 0, server_cpu_percent = 0, join_s = 0, late_p95_ms = 0;
  std::string error;
};

// Vehicle v of the fleet as its own process (this binary with --replay-vehicle), as real
// vehicles are: Cyclone 0.10.2 refuses a second identity's endpoints in one process.
struct FleetFlags {
  int vehicles = 32, streams = 4;
  double seconds = 30;
  std::string record_dir;
};

FleetCost fleetCost(const FleetFlags& flags, const Deployment& d, bool secured, int domain) {
  FleetCost cost;
  std::vector<std::string> server_args;
  if (secured) server_args = {"--security", d.server()};
  ServerProcess server(domain, server_args);
  const std::string logs = makeTempDir("stereomap-bench-fleet");
  // Every vehicle joins (its handshakes with the server on a loaded machine) before the clock.
  const auto start_at = std::chrono::system_clock::now() + 10s + flags.vehicles * 500ms;
  const auto start_ms =
      std::chrono::duration_cast<std::chrono::milliseconds>(start_at.time_since_epoch()).count();
  std::vector<std::unique_ptr<ChildProcess>> vehicles;
  for (int v = 0; v < flags.vehicles; ++v) {
    std::vector<std::string> argv = {kBin + "/stereomap-bench-security",
                                     "--replay-vehicle",
                                     std::to_string(v),
                                     "--vehicles",
                                     std::to_string(flags.vehicles),
                                     "--streams",
                                     std::to_string(flags.streams),
                                     "--fleet-seconds",
                                     std::to_string(flags.seconds),
                                     "--record-dir",
                                     flags.record_dir,
                                     "--start-at",
                                     std::to_string(start_ms),
                                     "--domain",
                                     std::to_string(domain)};
    if (secured) argv.insert(argv.end(), {"--security", d.vehicle("f" + std::to_string(v))});
    vehicles.push_back(
        std::make_unique<ChildProcess>(argv, logs + "/vehicle-" + std::to_string(v) + ".log"));
  }
  std::this_thread::sleep_until(start_at);
  const double before = processCpuSeconds(server.process().pid());
  std::this_thread::sleep_until(
      start_at + std::chrono::milliseconds(static_cast<int64_t>(flags.seconds * 1000)));
  cost.server_cpu_percent =
      100 * (processCpuSeconds(server.process().pid()) - before) / flags.seconds;
  std::vector<double> late;
  for (int v = 0; v < flags.vehicles; ++v) {
    const int code = vehicles[static_cast<size_t>(v)]->waitExit(120s).value_or(-1);
    const std::string log = readText(logs + "/vehicle-" + std::to_string(v) + ".log");
    std::smatch match;
    static const std::regex pattern(R"re(late p95 ([\d.]+) ms, joined in ([\d.]+) s)re");
    if (code != 0 || !std::regex_search(log, match, pattern)) {
      if (cost.error.empty()) cost.error = "vehicle " + std::to_string(v) + ": " + log;
      continue;
    }
    late.push_back(std::stod(match[1]));
    cost.join_s = std::max(cost.join_s, std::stod(match[2]));
  }
  if (!late.empty()) cost.late_p95_ms = *std::max_element(late.begin(), late.end());
  const auto listed = json::parse(server.get("/api/sessions").body, nullptr, false);
  if (listed.is_array()) {
    for (const auto& session : listed) {
      if (session.value("frames", 0) <= 0) continue;
      ++cost.sessions;
      cost.lag_p95_ms = std::max(cost.lag_p95_ms, session["publish_lag_ms"].value("p95", 0.0));
    }
  }
  fs::remove_all(logs);
  return cost;
}

// The child's side: vehicle `v` alone, from `start_ms` (since the epoch).
int replayVehicle(const FleetFlags& flags, int v, int64_t start_ms, int domain,
                  const std::string& identity) {
  const auto streams = bench::fleetStreams(flags.record_dir, flags.streams, 400, kRecordDomain);
  std::vector<std::string> ids, identities;
  for (int i = 0; i < flags.vehicles; ++i) {
    ids.push_back("f" + std::to_string(i));
    identities.push_back(i == v ? identity : "");
  }
  if (identity.empty()) identities.clear();
  const auto run = bench::replayOverDds(
      streams, flags.vehicles, flags.seconds,
      {.domain_id = static_cast<uint32_t>(domain), .config_file = STEREOMAP_DDS_CONFIG}, ids,
      identities, v, std::chrono::system_clock::time_point(std::chrono::milliseconds(start_ms)));
  if (!run.error.empty()) {
    std::printf("replay failed: %s\n", run.error.c_str());
    return 1;
  }
  std::printf("replayed %llu clouds and %llu poses, late p95 %.1f ms, joined in %.1f s\n",
              static_cast<unsigned long long>(run.clouds),
              static_cast<unsigned long long>(run.poses), run.late_p95_ms, run.join_s);
  return 0;
}

// ---- 4. TLS ------------------------------------------------------------------------------

// "tls first view W ms, plain V ms" from tls_clients.mjs; {-1, -1} when it failed.
std::pair<double, double> tlsFirstView(int rounds) {
  const auto run = runTool({"/usr/bin/node", STEREOMAP_TLS_CLIENTS, "--bin-dir", kBin,
                            "--dds-config", STEREOMAP_DDS_CONFIG, "--domain",
                            std::to_string(kTlsDomain), "--measure", std::to_string(rounds)},
                           600s);
  std::smatch match;
  static const std::regex pattern(R"re(tls first view (\d+) ms, plain (\d+) ms)re");
  if (!std::regex_search(run.output, match, pattern)) {
    std::fprintf(stderr, "tls_clients.mjs failed:\n%s\n", run.output.c_str());
    return {-1, -1};
  }
  std::fprintf(stderr, "%s", run.output.c_str());
  return {std::stod(match[1]), std::stod(match[2])};
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "stereomap-bench-security: the attacks a secured deployment refuses and what security "
      "costs, side by side with the same deployment open (issue 55)"};
  int vehicles = 32, frames = 200, runs = 2, streams = 4, tls_rounds = 5;
  double fleet_seconds = 30;
  std::string record_dir;
  app.add_option("--vehicles", vehicles, "the fleet's size")
      ->check(CLI::Range(1, 64))
      ->capture_default_str();
  app.add_option("--fleet-seconds", fleet_seconds, "length of each fleet run")
      ->check(CLI::Range(5.0, 600.0))
      ->capture_default_str();
  app.add_option("--frames", frames, "frames of each single-vehicle flight (10 Hz)")
      ->check(CLI::Range(20, 3000))
      ->capture_default_str();
  app.add_option("--runs", runs, "open/secured pairs of each single-vehicle flight")
      ->check(CLI::Range(1, 10))
      ->capture_default_str();
  app.add_option("--streams", streams, "distinct recorded streams the fleet replays")
      ->check(CLI::Range(1, 32))
      ->capture_default_str();
  app.add_option("--record-dir", record_dir,
                 "where the fleet's recorded streams are kept (default: a temporary folder)");
  app.add_option("--tls-rounds", tls_rounds, "first views timed over each of https and http")
      ->check(CLI::Range(1, 50))
      ->capture_default_str();
  std::string only;
  app.add_option("--only", only, "one part alone (its figures only; the last line still printed)")
      ->check(CLI::IsMember({"attacks", "cost", "fleet", "tls"}));
  int replay_vehicle = -1, domain = 0;
  int64_t start_ms = 0;
  std::string identity;
  auto* internal = app.add_option_group("internal", "one vehicle of the fleet (the bench's own)");
  internal->add_option("--replay-vehicle", replay_vehicle)->group("");
  internal->add_option("--start-at", start_ms)->group("");
  internal->add_option("--domain", domain)->group("");
  internal->add_option("--security", identity)->group("");
  if (auto exit_code = common::parseCommandLine(app, argc, argv)) return *exit_code;
  spdlog::set_level(spdlog::level::warn);
  FleetFlags fleet_flags{vehicles, streams, fleet_seconds, record_dir};
  if (replay_vehicle >= 0) {
    return replayVehicle(fleet_flags, replay_vehicle, start_ms, domain, identity);
  }

  std::vector<std::string> fleet_ids = {"v1", "v2"};
  for (int v = 0; v < vehicles; ++v) fleet_ids.push_back("f" + std::to_string(v));
  std::fprintf(stderr, "making a deployment: %zu vehicle identities...\n", fleet_ids.size());
  const Deployment d = makeDeployment(fleet_ids);
  if (!d.ok) {
    std::fprintf(stderr, "stereomap-certs failed:\n%s\n", d.log.c_str());
    return 1;
  }

  auto part = [&](const char* name) { return only.empty() || only == name; };
  Attacks a;
  if (part("attacks")) attacks(d, a);

  Cost totals[2][2];  // [whole][secured]
  for (int r = 0; r < (part("cost") ? runs : 0); ++r) {
    for (bool whole : {false, true}) {
      for (bool secured : {false, true}) {
        const Cost c = flightCost(d, secured, whole, frames);
        std::fprintf(stderr,
                     "flight %d %s %s: %.1f kB on the wire, vehicle CPU %.2f s, server CPU %.2f s, "
                     "%llu samples in %.1f s (%.1f/s, %.2f ms server CPU each)\n",
                     r + 1, whole ? "whole clouds" : "thinned", secured ? "secured" : "open",
                     c.link_bytes / 1e3, c.vehicle_cpu_s, c.server_cpu_s,
                     static_cast<unsigned long long>(c.samples), c.seconds,
                     c.samples / std::max(c.seconds, 1e-9),
                     1000 * c.server_cpu_s / std::max<double>(1, c.samples));
        auto& t = totals[whole][secured];
        t.link_bytes += c.link_bytes;
        t.vehicle_cpu_s += c.vehicle_cpu_s;
        t.server_cpu_s += c.server_cpu_s;
        t.samples += c.samples;
        t.seconds += c.seconds;
      }
    }
  }
  for (bool whole : {false, true}) {
    const auto& open = totals[whole][0];
    const auto& sec = totals[whole][1];
    std::printf(
        "%s stream: link %+.1f%%, vehicle CPU %+.1f%%, server CPU %+.1f%% (%.2f against %.2f ms "
        "per sample), samples %llu against %llu\n",
        whole ? "whole-cloud" : "thinned", percentMore(sec.link_bytes, open.link_bytes),
        percentMore(sec.vehicle_cpu_s, open.vehicle_cpu_s),
        percentMore(sec.server_cpu_s, open.server_cpu_s),
        1000 * sec.server_cpu_s / std::max<double>(1, sec.samples),
        1000 * open.server_cpu_s / std::max<double>(1, open.samples),
        static_cast<unsigned long long>(sec.samples),
        static_cast<unsigned long long>(open.samples));
  }
  // The figure's link and CPU: the thinned stream, what vehicles send by default.
  const auto& open = totals[0][0];
  const auto& sec = totals[0][1];

  const bool temporary = record_dir.empty();
  const fs::path dir =
      temporary ? fs::path(makeTempDir("stereomap-bench-security-streams")) : fs::path(record_dir);
  fleet_flags.record_dir = dir.string();
  if (part("fleet")) (void)bench::fleetStreams(dir, streams, 400, kRecordDomain);  // once, here
  FleetCost fleets[2];
  for (bool secured : {false, true}) {
    if (!part("fleet")) break;
    auto& f = fleets[secured];
    f = fleetCost(fleet_flags, d, secured, kFleetDomain + (secured ? 1 : 0));
    std::printf(
        "fleet of %d %s: %d sessions served, lag p95 %.1f ms (worst session), server CPU %.0f%%, "
        "joined in %.1f s, feeders late p95 %.1f ms%s\n",
        vehicles, secured ? "secured" : "open", f.sessions, f.lag_p95_ms, f.server_cpu_percent,
        f.join_s, f.late_p95_ms, f.error.empty() ? "" : (": " + f.error).c_str());
  }
  if (temporary) fs::remove_all(dir);

  const auto [tls_ms, plain_ms] =
      part("tls") ? tlsFirstView(tls_rounds) : std::pair<double, double>{-1, -1};
  std::printf("first view: tls %.0f ms, plain %.0f ms (%.2fx)\n", tls_ms, plain_ms,
              plain_ms > 0 ? tls_ms / plain_ms : 0.0);
  fs::remove_all(d.dir);

  const int authenticated = fleets[1].sessions + (sec.samples > 0 ? 1 : 0);
  std::printf(
      "security: %d vehicles authenticated, %d/%d attacks refused; link %+.1f%%, vehicle CPU "
      "%+.1f%%, server CPU %+.1f%%; fleet of %d secured: lag p95 %.0f ms; tls first view %.0f ms\n",
      authenticated, a.refused, a.tried, percentMore(sec.link_bytes, open.link_bytes),
      percentMore(sec.vehicle_cpu_s, open.vehicle_cpu_s),
      percentMore(fleets[1].server_cpu_percent, fleets[0].server_cpu_percent), fleets[1].sessions,
      fleets[1].lag_p95_ms, tls_ms);
  return 0;
}
