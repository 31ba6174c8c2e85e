// stereomap-bench-cluster (issue 39): the cluster on loopback, everything real: a throwaway
// PostgreSQL (as an unprivileged user), two stereomap-server --cluster processes, nginx in
// front of them (config/nginx), sim vehicles over DDS.
//   - failover: four vehicles in four sessions, two per server; one server killed with SIGKILL
//     mid-flight. Seconds until every session has a live owner (F), until a sample of each
//     taken session is committed again (I), until a viewer reconnecting through nginx gets a
//     tile of the killed server's session (V); when the flights end, the samples the vehicles
//     sent that are not in the journal (L) and those journaled twice (D).
//   - fenced: the killed server back, two more vehicles placed on it; it is paused (SIGSTOP)
//     past its lease and woken: rows committed with a stale epoch after the takeover (W).
//   - tiles: the Freiburg campus imported into the cluster; fifty clients fetch every tile
//     through nginx twice; the second pass's share of nginx cache hits (H).
//   - load: virtual vehicles replaying a recorded thinned stream (poses and clouds as a sim
//     vehicle sends them) at --rate samples/s for --seconds into both servers: the servers'
//     commit p99 (their /metrics, the newest 32768 commits) and the rate committed (R, rows in
//     the database during the window).
// The last line is the figure line. --series FILE: the failover's samples committed
// over time, per session, as CSV (failoverSeries), for scripts/plot-benchmarks.
//
//   stereomap-bench-cluster [--rate 2000] [--seconds 20] [--vehicles 16] [--only failover,...]
//                           [--series FILE]
#include <CLI/CLI.hpp>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <random>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <signal.h>

#include "common/time.hpp"
#include "proto/dds.hpp"
#include "server/cluster/cluster_journal.hpp"
#include "tests/support/cluster_check.hpp"
#include "tests/support/cluster_harness.hpp"
#include "tests/support/stream_count.hpp"

namespace {

using namespace stereomap;
using namespace std::chrono_literals;
using Clock = std::chrono::steady_clock;

constexpr int kDomain = 107, kLoadDomain = 108;

double secondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

// psql's answer without its trailing newline (a value to put back into a statement).
std::string trimmed(std::string text) {
  while (!text.empty() && (text.back() == '\n' || text.back() == ' ')) text.pop_back();
  return text;
}

struct Figures {
  double failover_s = -1, resumed_s = -1, viewer_s = -1;
  long lost = 0, duplicated = 0;
  long fenced_writes = -1;
  double cache_hits = -1;
  double commit_p99_ms = -1, rate = -1;
};

// Samples of sessions flight<first>..flight<first+count-1> sent but not journaled, and
// journaled twice.
void countLosses(testing::ClusterHarness& cluster, int first, int count, Figures& f) {
  for (int i = first; i < first + count; ++i) {
    const std::string session = "flight" + std::to_string(i);
    const auto sent = testing::sentBy(testing::readText(cluster.vehicleLog(i)));
    auto journal = cluster::ClusterJournal::open(cluster.db().url());
    if (!journal) continue;
    auto stored = (*journal)->read(session);
    if (!stored) continue;
    const auto journaled = testing::samplesIn(stored->records);
    f.lost += static_cast<long>(sent.poses + sent.clouds) -
              static_cast<long>(journaled.poseCount() + journaled.cloudCount());
    f.duplicated += static_cast<long>(journaled.repeated);
    std::fprintf(stderr, "%s: %zu/%zu poses, %zu/%zu clouds journaled, %zu twice\n",
                 session.c_str(), journaled.poseCount(), sent.poses, journaled.cloudCount(),
                 sent.clouds, journaled.repeated);
  }
}

// The flights' samples committed per half second and session, timed from the kill
// (`killed_at`, on the database's clock): when each session's commits stop and start again.
// `owners`: who had each session before the kill.
void failoverSeries(testing::ClusterHarness& cluster, const std::string& killed_at,
                    const std::map<std::string, std::string>& owners, const std::string& victim,
                    const std::string& path) {
  std::ofstream out(path);
  out << "session,on_killed_server,bin_start_s,bin_s,samples_committed\n";
  std::istringstream rows(cluster.query(
      "SELECT session, (floor(extract(epoch FROM committed_at - '" + killed_at +
      "'::timestamptz) * 2) / 2)::float8 AS bin, count(*) FROM sm_journal WHERE session LIKE "
      "'flight%' GROUP BY session, bin ORDER BY session, bin"));
  for (std::string line; std::getline(rows, line);) {
    std::istringstream fields(line);
    std::string session, bin, count;
    std::getline(fields, session, '|');
    std::getline(fields, bin, '|');
    std::getline(fields, count);
    const auto owner = owners.find(session);
    out << session << ',' << (owner != owners.end() && owner->second == victim) << ',' << bin
        << ",0.5," << count << '\n';
  }
  if (!out) std::fprintf(stderr, "failover: cannot write %s\n", path.c_str());
}

void failover(testing::ClusterHarness& cluster, Figures& f, const std::string& series_path) {
  cluster.startServer(kDomain, "a");
  cluster.startServer(kDomain, "b");
  std::string why;
  if (!cluster.startNginx(&why)) {
    std::fprintf(stderr, "nginx: %s\n", why.c_str());
    return;
  }
  for (int i = 0; i < 4; ++i) cluster.startVehicle(kDomain, i, 300);
  testing::waitUntil(30s, [&] { return cluster.owners().size() == 4; });
  std::this_thread::sleep_for(8s);
  const int proxy = cluster.nginx().port();
  if (!testing::viewerSeesTiles(proxy, "flight0", 10s)) {
    std::fprintf(stderr, "failover: no viewer through nginx before the kill\n");
  }
  const std::string victim = cluster.owners()["flight0"];
  const std::string survivor = victim == "a" ? "b" : "a";
  const auto owners = cluster.owners();
  size_t taken = 0;
  for (const auto& [session, owner] : owners) taken += owner == victim;
  // The kill's moment on the commits' clock (the database's), for --series.
  const std::string killed_at = trimmed(cluster.query("SELECT clock_timestamp()"));
  cluster.server(victim).process().kill9();
  const auto killed = Clock::now();
  std::atomic<bool> seen{false};
  std::thread viewer([&] {  // reconnecting as the web viewer does, every 200 ms
    while (!seen && secondsSince(killed) < 60) {
      if (testing::viewerSeesTiles(proxy, "flight0", 2s)) {
        f.viewer_s = secondsSince(killed);
        seen = true;
      } else {
        std::this_thread::sleep_for(200ms);
      }
    }
  });
  if (testing::waitUntil(
          60s, [&] { return cluster.allOwnedBy(survivor); }, 50ms)) {
    f.failover_s = secondsSince(killed);
  }
  if (testing::waitUntil(
          60s,
          [&] {
            return cluster.query(
                       "SELECT count(DISTINCT session) FROM sm_journal WHERE epoch > 2") ==
                   std::to_string(taken) + "\n";
          },
          50ms)) {
    f.resumed_s = secondsSince(killed);
  }
  viewer.join();
  std::fprintf(stderr, "failover %.1f s, ingest resumed %.1f s, viewer back %.1f s\n", f.failover_s,
               f.resumed_s, f.viewer_s);
  if (!cluster.waitForVehicles(180s, &why))
    std::fprintf(stderr, "a vehicle failed: %s\n", why.c_str());
  countLosses(cluster, 0, 4, f);
  if (!series_path.empty()) failoverSeries(cluster, killed_at, owners, victim, series_path);
}

void fenced(testing::ClusterHarness& cluster, Figures& f) {
  // The killed server back (the same name), and two new flights: the least loaded takes them.
  cluster.servers().erase("a");
  cluster.servers().erase("b");
  cluster.startServer(kDomain, "a");
  cluster.startServer(kDomain, "b");
  std::string why;
  if (!cluster.startNginx(&why)) std::fprintf(stderr, "nginx: %s\n", why.c_str());  // new ports
  for (int i = 4; i < 6; ++i) cluster.startVehicle(kDomain, i, 250);
  testing::waitUntil(30s, [&] { return cluster.owners().size() >= 6; });
  std::this_thread::sleep_for(5s);
  const std::string stale = cluster.owners()["flight4"];
  const std::string other = stale == "a" ? "b" : "a";
  ::kill(cluster.server(stale).process().pid(), SIGSTOP);
  testing::waitUntil(
      30s, [&] { return cluster.allOwnedBy(other); }, 100ms);
  std::this_thread::sleep_for(2s);
  ::kill(cluster.server(stale).process().pid(), SIGCONT);
  testing::waitUntil(20s, [&] {
    return cluster.server(stale).get("/api/sessions/flight4").status == 404 &&
           cluster.server(stale).get("/api/sessions/flight5").status == 404;
  });
  if (!cluster.waitForVehicles(180s, &why))
    std::fprintf(stderr, "a vehicle failed: %s\n", why.c_str());
  const std::string rows = cluster.query(
      "SELECT count(*) FROM sm_journal j JOIN sm_sessions s ON s.id = j.session "
      "WHERE j.epoch < s.epoch AND j.committed_at >= s.owned_since");
  f.fenced_writes = rows.empty() ? -1 : std::stol(rows);
  std::fprintf(stderr,
               "fenced: %ld rows with a stale epoch after the takeover; the stale server %s\n",
               f.fenced_writes,
               cluster.server(stale).log().find("fenced") != std::string::npos
                   ? "logged that it was fenced"
                   : "did NOT log that it was fenced");
  countLosses(cluster, 4, 2, f);
}

void tileCache(testing::ClusterHarness& cluster, const std::filesystem::path& campus, Figures& f) {
  const auto imported =
      testing::runTool({std::string(STEREOMAP_BIN_DIR) + "/stereomap-store", "--cluster",
                        cluster.db().url(), "import", campus.string(), "--session", "campus"},
                       120s);
  if (imported.exit_code != 0) {
    std::fprintf(stderr, "import failed: %s\n", imported.output.c_str());
    return;
  }
  const int proxy = cluster.nginx().port();
  std::vector<std::string> urls;
  testing::waitUntil(60s, [&] {
    const auto index = testing::httpGet(proxy, "/api/sessions/campus/tiles");
    if (index.status != 200) return false;
    const auto listed = nlohmann::json::parse(index.body);
    urls.clear();
    for (const auto& tile : listed["tiles"]) urls.push_back(tile["url"]);
    return urls.size() > 1000;
  });
  if (urls.empty()) std::fprintf(stderr, "tiles: the campus was not served through nginx\n");
  constexpr int kClients = 50;
  std::atomic<size_t> ok[2] = {0, 0}, hits[2] = {0, 0};
  for (int pass = 0; pass < 2; ++pass) {
    const auto start = Clock::now();
    std::vector<std::thread> clients;
    for (int c = 0; c < kClients; ++c) {
      clients.emplace_back([&, c, pass] {
        testing::HttpConnection connection(proxy);
        for (size_t i = 0; i < urls.size(); ++i) {
          const auto reply = connection.get(urls[(i + static_cast<size_t>(c) * 53) % urls.size()]);
          if (reply.status != 200) continue;
          ++ok[pass];
          if (reply.header("X-Cache-Status") == "HIT") ++hits[pass];
        }
      });
    }
    for (auto& client : clients) client.join();
    std::fprintf(stderr, "tiles pass %d: %zu tiles x %d clients, %zu ok, %zu cache hits, %.1f s\n",
                 pass + 1, urls.size(), kClients, ok[pass].load(), hits[pass].load(),
                 secondsSince(start));
  }
  if (!urls.empty()) {
    f.cache_hits =
        100.0 * static_cast<double>(hits[1]) / static_cast<double>(urls.size() * kClients);
  }
}

// Virtual vehicles replaying `flight` at `rate` samples/s in all, each in its own session
// partition, with its own stream and seqs.
void load(testing::ClusterHarness& cluster,
          const std::vector<proto::journal::JournalRecord>& flight, double rate, double seconds,
          int vehicles, Figures& f) {
  if (flight.empty()) {
    std::fprintf(stderr, "load: no recorded flight\n");
    return;
  }
  cluster.servers().clear();
  // The earlier phases' sessions closed: the load's servers serve its sessions alone.
  cluster.query("UPDATE sm_sessions SET state = 'closed', owner = NULL");
  cluster.startServer(kLoadDomain, "a", 4);
  cluster.startServer(kLoadDomain, "b", 4);
  auto participant =
      proto::Participant::create({.domain_id = kLoadDomain, .config_file = STEREOMAP_DDS_CONFIG});
  if (!participant) return;
  struct Vehicle {
    std::string id, session;
    uint64_t stream = 0, poses = 0, clouds = 0;
    size_t next = 0;
    std::unique_ptr<proto::Writer<proto::PoseMsg>> pose_writer;
    std::unique_ptr<proto::Writer<proto::CloudFrameMsg>> cloud_writer;
    std::unique_ptr<proto::Writer<proto::SessionEventMsg>> event_writer;
  };
  std::vector<Vehicle> fleet(static_cast<size_t>(vehicles));
  std::mt19937_64 random(7);
  for (int i = 0; i < vehicles; ++i) {
    auto& v = fleet[static_cast<size_t>(i)];
    v.id = "load-v" + std::to_string(i);
    v.session = "load" + std::to_string(i);
    v.stream = random() | 1;
    const std::vector<std::string> partition = {proto::vehiclePartition(v.session, v.id)};
    auto poses = proto::Writer<proto::PoseMsg>::create(*participant, partition);
    auto clouds = proto::Writer<proto::CloudFrameMsg>::create(*participant, partition);
    auto events = proto::Writer<proto::SessionEventMsg>::create(*participant, partition);
    if (!poses || !clouds || !events) {
      std::fprintf(stderr, "load: cannot create DDS writers\n");
      return;
    }
    v.pose_writer = std::move(poses).value();
    v.cloud_writer = std::move(clouds).value();
    v.event_writer = std::move(events).value();
    proto::SessionEventMsg started;
    started.vehicle_id = v.id;
    started.session_id = v.session;
    started.stream = v.stream;
    started.kind = proto::SessionEventKind::kStarted;
    started.stamp_ns = common::nowNs();
    started.resolution_hint = 0.1;
    (void)v.event_writer->write(started);
  }
  // Every session placed and served before the clock starts.
  testing::waitUntil(60s, [&] {
    return cluster.query(
               "SELECT count(*) FROM sm_sessions WHERE id LIKE 'load%' AND owner "
               "IS NOT NULL") == std::to_string(vehicles) + "\n";
  });
  std::this_thread::sleep_for(3s);
  const std::string t0 = cluster.query("SELECT clock_timestamp()");
  const auto start = Clock::now();
  size_t sent = 0;
  const auto slice = 10ms;
  for (auto due = start; secondsSince(start) < seconds; due += slice) {
    std::this_thread::sleep_until(due);
    const auto target = static_cast<size_t>(rate * secondsSince(start));
    while (sent < target) {
      auto& v = fleet[sent % fleet.size()];
      auto record = flight[v.next % flight.size()];
      ++v.next;
      // As the vehicle's own: its ids, its stream, the next seq of the topic, stamped now.
      auto restamp = [&](auto& message, uint64_t& next_seq, auto& writer) {
        message.vehicle_id = v.id;
        message.session_id = v.session;
        message.stream = v.stream;
        message.seq = next_seq++;
        message.unacked_from = 0;
        message.stamp_ns = common::nowNs();
        (void)writer->write(message);
      };
      if (auto* pose = std::get_if<proto::PoseMsg>(&record)) {
        restamp(*pose, v.poses, v.pose_writer);
      } else if (auto* cloud = std::get_if<proto::CloudFrameMsg>(&record)) {
        restamp(*cloud, v.clouds, v.cloud_writer);
      }
      ++sent;
    }
  }
  const double sent_s = secondsSince(start);
  std::this_thread::sleep_for(1s);  // what was sent last, committed
  const std::string t1 = cluster.query("SELECT clock_timestamp()");
  const std::string committed = cluster.query(
      "SELECT count(*), extract(epoch FROM max(committed_at) - min(committed_at)) FROM sm_journal "
      "WHERE session LIKE 'load%' AND committed_at BETWEEN '" +
      trimmed(t0) + "' AND '" + trimmed(t1) + "'");
  const auto bar = committed.find('|');
  if (bar != std::string::npos) {
    const double rows = std::stod(committed.substr(0, bar));
    const double span = std::stod(committed.substr(bar + 1));
    f.rate = span > 0 ? rows / span : -1;
  }
  for (const auto& [id, server] : cluster.servers()) {
    const std::string metrics = server->get("/metrics").body;
    auto series = [&](const std::string& name) { return testing::seriesValue(metrics, name); };
    const double p99 = series("stereomap_cluster_commit_seconds{quantile=\"0.99\"}");
    f.commit_p99_ms = std::max(f.commit_p99_ms, p99 * 1000);
    std::fprintf(stderr,
                 "load: server %s commit p50 %.1f ms, p99 %.1f ms, max %.1f ms; %.0f samples in "
                 "%.0f commits\n",
                 id.c_str(), series("stereomap_cluster_commit_seconds{quantile=\"0.5\"}") * 1000,
                 p99 * 1000, series("stereomap_cluster_commit_seconds{quantile=\"1\"}") * 1000,
                 series("stereomap_cluster_committed_samples_total"),
                 series("stereomap_cluster_commit_groups_total"));
  }
  std::fprintf(stderr,
               "load: %zu samples sent in %.1f s (%.0f/s) by %d vehicles; %.0f/s committed\n", sent,
               sent_s, static_cast<double>(sent) / sent_s, vehicles, f.rate);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "stereomap-bench-cluster: failover, fencing, nginx's tile cache and commit "
      "latency of the cluster on PostgreSQL (issue 39)"};
  double rate = 2000, seconds = 20;
  int vehicles = 16;
  std::string only = "failover,fenced,tiles,load";
  std::string campus = std::string(STEREOMAP_DATA_DIR) + "/octomap_samples/fr_campus.bt";
  app.add_option("--rate", rate, "Samples per second the load's vehicles send in all")
      ->capture_default_str();
  app.add_option("--seconds", seconds, "How long the load runs")->capture_default_str();
  app.add_option("--vehicles", vehicles, "Virtual vehicles of the load (a session each)")
      ->check(CLI::Range(1, 64))
      ->capture_default_str();
  app.add_option("--only", only, "Comma-separated phases: failover,fenced,tiles,load")
      ->capture_default_str();
  app.add_option("--campus", campus, "The campus map for the tile phase")->capture_default_str();
  std::string series_path;
  app.add_option("--series", series_path,
                 "Write the failover's samples committed per session over time to this CSV file");
  CLI11_PARSE(app, argc, argv);
  auto want = [&](const char* phase) { return only.find(phase) != std::string::npos; };

  std::string why;
  auto cluster = testing::ClusterHarness::start(&why);
  if (!cluster) {
    std::fprintf(stderr, "cannot start PostgreSQL: %s\n", why.c_str());
    return 1;
  }
  Figures f;
  if (want("failover") || want("load"))
    failover(*cluster, f, series_path);  // load replays its flight
  if (want("fenced")) fenced(*cluster, f);
  if (want("tiles")) {
    if (std::filesystem::exists(campus)) {
      tileCache(*cluster, campus, f);
    } else {
      std::fprintf(stderr, "tiles: %s is absent; skipped\n", campus.c_str());
    }
  }
  if (want("load"))
    load(*cluster, testing::recordedFlight(*cluster, "flight1"), rate, seconds, vehicles, f);
  std::printf(
      "cluster: failover %.1f s, ingest resumed %.1f s, viewer back %.1f s; lost %ld, "
      "duplicated %ld; fenced writes %ld; tile cache hits %.1f%%; commit p99 %.1f ms at %.0f "
      "samples/s\n",
      f.failover_s, f.resumed_s, f.viewer_s, f.lost, f.duplicated, f.fenced_writes, f.cache_hits,
      f.commit_p99_ms, f.rate);
  return 0;
}
