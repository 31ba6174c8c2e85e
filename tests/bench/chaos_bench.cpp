// stereomap-bench-chaos: the cluster under faults drawn at random for many minutes, in the
// spirit of Jepsen, everything real on loopback: PostgreSQL under Patroni (a primary with
// synchronous standbys, etcd), stereomap-server --cluster processes, nginx, sim vehicles.
//   - schedule: vehicles fly one session after another; every --interval seconds (jittered) a
//     fault, each kind in turn in a shuffled order so that every kind comes as often: a server
//     killed (-9) and started again; a server paused past its lease and resumed; a server
//     paused, a new process started under its id, the old one resumed (it must step down); the
//     database primary killed (Patroni fails over: P, seconds until samples commit again); the
//     primary hung for 20 s; nginx killed and started again. At the end every flight is checked:
//     each sample the vehicle sent journaled once (L lost, D duplicated), each pose of its
//     --trajectory-out journaled, each live map equal to its journal fused offline; G: the
//     longest time between two commits of one session while it flew.
//   - takeover: --history-sessions sessions with --history-minutes of history each (a real sim
//     flight repeated, written through the cluster's own journal, snapshots as a server writes
//     them), served by one server that is then killed: seconds until another serves them all (F).
//   - control: --control-servers servers and --control-sessions live sessions: statements each
//     server sends per second to keep its lease and to see who owns what (Q).
// The last line is the figure line.
//
//   stereomap-bench-chaos [--minutes 20] [--interval 30] [--only schedule,takeover,control]
#include <signal.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <map>
#include <mutex>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "common/time.hpp"
#include "server/cluster/cluster_db.hpp"
#include "server/cluster/cluster_journal.hpp"
#include "tests/support/cluster_check.hpp"
#include "tests/support/cluster_harness.hpp"
#include "tests/support/stream_count.hpp"

namespace {

using namespace stereomap;
using namespace std::chrono_literals;
using Clock = std::chrono::steady_clock;

constexpr int kScheduleDomain = 111, kTakeoverDomain = 112, kControlDomain = 113;

double secondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

std::string firstLine(const std::string& text) { return text.substr(0, text.find('\n')); }

struct Figures {
  double minutes = 0;
  int faults = 0;
  long samples = 0, lost = 0, duplicated = 0;
  double longest_gap_s = -1, database_failover_s = -1;
  double history_min = 0, takeover_s = -1;
  double control_per_server = -1;
};

enum class Fault {
  kServerKilled,
  kServerPaused,
  kServerRestartedWhilePaused,
  kPrimaryKilled,
  kDatabaseHung,
  kNginxRestarted
};
constexpr Fault kFaults[] = {
    Fault::kServerKilled,  Fault::kServerPaused, Fault::kServerRestartedWhilePaused,
    Fault::kPrimaryKilled, Fault::kDatabaseHung, Fault::kNginxRestarted};

const char* faultName(Fault fault) {
  switch (fault) {
    case Fault::kServerKilled:
      return "server killed";
    case Fault::kServerPaused:
      return "server paused past its lease";
    case Fault::kServerRestartedWhilePaused:
      return "server restarted under its id while paused";
    case Fault::kPrimaryKilled:
      return "database primary killed";
    case Fault::kDatabaseHung:
      return "database primary hung 20 s";
    case Fault::kNginxRestarted:
      return "nginx killed and restarted";
  }
  return "?";
}

struct ScheduleOptions {
  double minutes = 20, interval_s = 30;
  int vehicles = 3, flight_frames = 1200, servers = 3, database_nodes = 3;
  double lease_s = 2;
  uint64_t seed = 1;
};

// Vehicles flying one session after another until told to stop: vehicle slot k flies
// flight<i> for ever new i.
class Fleet {
 public:
  Fleet(testing::ClusterHarness& cluster, int domain, int slots, int frames)
      : cluster_(cluster), domain_(domain), frames_(frames), flying_(slots, -1) {}
  // Starts a flight in every idle slot (while launching); call every second or so.
  void tend(bool launching) {
    std::lock_guard lock(mutex_);
    for (auto& flight : flying_) {
      if (flight >= 0 && cluster_.vehicle(flight).running()) continue;
      flight = -1;
      if (!launching) continue;
      flight = flights_++;
      cluster_.startVehicle(domain_, flight, frames_);
    }
  }
  int flights() const { return flights_; }

 private:
  testing::ClusterHarness& cluster_;
  int domain_, frames_;
  std::mutex mutex_;
  std::vector<int> flying_;  // the flight each slot flies, -1: none
  int flights_ = 0;
};

// Seconds until any sample commits later than `after` (the database's clock), -1 when none
// within a minute.
double untilCommitsAfter(testing::ClusterHarness& cluster, const std::string& after,
                         Clock::time_point since) {
  const bool resumed = testing::waitUntil(
      60s,
      [&] {
        return cluster.query("SELECT count(*) > 0 FROM sm_journal WHERE committed_at > '" + after +
                             "'") == "t\n";
      },
      100ms);
  return resumed ? secondsSince(since) : -1;
}

void schedule(const ScheduleOptions& o, Figures& f) {
  std::string why;
  auto cluster = testing::ClusterHarness::start(&why, o.database_nodes);
  if (!cluster) {
    std::fprintf(stderr, "schedule: cannot start the database: %s\n", why.c_str());
    return;
  }
  std::vector<std::string> names;
  for (int i = 0; i < o.servers; ++i) {
    names.push_back(std::string(1, static_cast<char>('a' + i)));
    cluster->startServer(kScheduleDomain, names.back(), o.lease_s);
  }
  if (!cluster->startNginx(&why)) {
    std::fprintf(stderr, "schedule: nginx: %s\n", why.c_str());
    return;
  }
  Fleet fleet(*cluster, kScheduleDomain, o.vehicles, o.flight_frames);
  std::atomic<bool> launching{true}, tending{true};
  std::thread tender([&] {
    while (tending) {
      fleet.tend(launching);
      std::this_thread::sleep_for(1s);
    }
  });

  std::mt19937_64 random(o.seed);
  std::vector<Fault> order;
  std::vector<std::unique_ptr<testing::ServerProcess>> superseded;
  std::map<Fault, int> count;
  const auto start = Clock::now();
  const double end_s = o.minutes * 60;
  std::uniform_real_distribution<double> jitter(0.7, 1.3);
  auto pick = [&](const std::vector<std::string>& from) {
    return from[std::uniform_int_distribution<size_t>(0, from.size() - 1)(random)];
  };
  for (double next_s = o.interval_s * jitter(random); next_s < end_s - 60;
       next_s += o.interval_s * jitter(random)) {
    std::this_thread::sleep_for(
        std::chrono::duration<double>(std::max(0.0, next_s - secondsSince(start))));
    if (order.empty()) {
      order.assign(std::begin(kFaults), std::end(kFaults));
      std::shuffle(order.begin(), order.end(), random);
    }
    const Fault fault = order.back();
    order.pop_back();
    ++count[fault];
    ++f.faults;
    const double at_s = secondsSince(start);
    std::string detail;
    try {
      switch (fault) {
        case Fault::kServerKilled: {
          const auto name = pick(names);
          cluster->server(name).process().kill9();
          std::this_thread::sleep_for(2s);  // a supervisor's restart delay
          cluster->startServer(kScheduleDomain, name, o.lease_s);
          detail = name;
          break;
        }
        case Fault::kServerPaused: {
          const auto name = pick(names);
          const pid_t pid = cluster->server(name).process().pid();
          ::kill(pid, SIGSTOP);
          std::this_thread::sleep_for(std::chrono::duration<double>(o.lease_s * 2 + 1));
          ::kill(pid, SIGCONT);
          detail = name;
          break;
        }
        case Fault::kServerRestartedWhilePaused: {
          const auto name = pick(names);
          auto old = cluster->takeServer(name);
          ::kill(old->process().pid(), SIGSTOP);
          cluster->startServer(kScheduleDomain, name, o.lease_s);
          std::this_thread::sleep_for(8s);
          ::kill(old->process().pid(), SIGCONT);
          superseded.push_back(std::move(old));
          detail = name;
          break;
        }
        case Fault::kPrimaryKilled: {
          const std::string before = firstLine(cluster->query("SELECT clock_timestamp()"));
          const auto killed = Clock::now();
          cluster->db().crash();
          const double resumed_s = untilCommitsAfter(*cluster, before, killed);
          f.database_failover_s = std::max(f.database_failover_s, resumed_s < 0 ? 1e9 : resumed_s);
          detail = "samples commit again after " + std::to_string(resumed_s) + " s";
          if (!cluster->db().restart(&why)) detail += "; NOT whole again: " + why;
          break;
        }
        case Fault::kDatabaseHung: {
          const std::string before = firstLine(cluster->query("SELECT clock_timestamp()"));
          const auto hung = Clock::now();
          cluster->db().pause();
          std::atomic<double> resumed_s{-1};
          std::thread watch([&] { resumed_s = untilCommitsAfter(*cluster, before, hung); });
          std::this_thread::sleep_for(20s);
          cluster->db().resume();
          watch.join();
          detail = "samples commit again after " + std::to_string(resumed_s.load()) + " s";
          if (!cluster->db().restart(&why)) detail += "; NOT whole again: " + why;
          break;
        }
        case Fault::kNginxRestarted:
          if (!cluster->nginx().restart(&why)) detail = "NOT started again: " + why;
          break;
      }
    } catch (const std::exception& error) {
      detail += std::string(" (failed: ") + error.what() + ")";
    }
    std::fprintf(stderr, "chaos: %6.1f s fault %d: %s %s\n", at_s, f.faults, faultName(fault),
                 detail.c_str());
  }
  std::this_thread::sleep_for(
      std::chrono::duration<double>(std::max(0.0, end_s - secondsSince(start))));
  f.minutes = secondsSince(start) / 60;
  launching = false;
  std::fprintf(stderr, "chaos: %.1f min, no more flights; waiting for the %d flown\n", f.minutes,
               fleet.flights());
  std::string vehicles_why;
  if (!cluster->waitForVehicles(300s, &vehicles_why)) {
    std::fprintf(stderr, "chaos: a vehicle failed: %s\n", vehicles_why.c_str());
  }
  tending = false;
  tender.join();
  for (auto& old : superseded) {
    const auto code = old->process().waitExit(10s);
    if (!code || *code != 1) {
      std::fprintf(stderr, "chaos: a superseded server did NOT step down (exit %d)\n",
                   code ? *code : -999);
    }
  }
  for (const auto& [fault, n] : count) std::fprintf(stderr, "chaos: %s x%d\n", faultName(fault), n);

  // G: the longest time between two commits of one flight.
  const std::string gap = cluster->query(
      "SELECT coalesce(max(gap), 0) FROM (SELECT extract(epoch FROM committed_at - "
      "lag(committed_at) OVER (PARTITION BY session ORDER BY committed_at)) AS gap "
      "FROM sm_journal WHERE session LIKE 'flight%') gaps");
  f.longest_gap_s = gap.empty() ? -1 : std::stod(gap);
  int incomplete = 0;
  for (int i = 0; i < fleet.flights(); ++i) {
    const auto check = testing::checkFlight(*cluster, i, /*with_map=*/true, 120s);
    f.samples += static_cast<long>(check.sent_poses + check.sent_clouds);
    f.lost += std::max(0L, check.lost()) + static_cast<long>(check.trajectory_missing);
    f.duplicated += static_cast<long>(check.repeated);
    if (!check.whole(/*with_map=*/true)) ++incomplete;
    std::fprintf(stderr, "chaos: %s\n", check.summary().c_str());
  }
  std::fprintf(stderr, "chaos: %d flights, %d not whole\n", fleet.flights(), incomplete);
}

// Writes `minutes` of flight (the recorded one repeated, renumbered and restamped at its own
// rate) into session `session` through the cluster's journal, with a snapshot (`map`) as its
// server writes them, the newest 30 s before the end.
bool writeHistory(cluster::ClusterJournal& journal, const std::string& session,
                  const std::vector<proto::journal::JournalRecord>& flight, const std::string& map,
                  double minutes) {
  size_t poses_per_pass = 0;
  for (const auto& record : flight)
    poses_per_pass += std::holds_alternative<proto::PoseMsg>(record);
  if (poses_per_pass == 0) return false;
  const auto poses_wanted = static_cast<size_t>(minutes * 60 * 10);  // 10 Hz
  const size_t records = flight.size() * poses_wanted / poses_per_pass;
  const int64_t start_ns = common::nowNs() - static_cast<int64_t>(minutes * 60e9);
  std::atomic<size_t> next{0};
  std::atomic<bool> failed{false};
  std::vector<std::thread> writers;
  const uint64_t stream = std::hash<std::string>{}(session) | 1;
  // Many appenders at once: the journal commits them in groups, as it does a fleet's.
  for (int w = 0; w < 48; ++w) {
    writers.emplace_back([&] {
      for (size_t i; (i = next++) < records && !failed;) {
        auto record = flight[i % flight.size()];
        auto restamp = [&](auto& message) {
          message.session_id = session;
          message.vehicle_id = "h";
          message.stream = stream;
          message.seq = i;  // one stream for both topics: seqs unique per topic either way
          message.unacked_from = 0;
          message.stamp_ns =
              start_ns + static_cast<int64_t>(i * 100'000'000 * poses_per_pass / flight.size());
          return journal.append(message);
        };
        auto appended = std::visit(
            [&](auto& message) -> common::Result<uint64_t> { return restamp(message); }, record);
        if (!appended) failed = true;
      }
    });
  }
  for (auto& writer : writers) writer.join();
  if (failed) return false;
  // The newest snapshot 30 s (300 poses' worth of records) before the end, the one before
  // 30 s earlier: as a server writing one every 30 s leaves them.
  const size_t per_30s = flight.size() * 300 / poses_per_pass;
  for (size_t back : {2 * per_30s, per_30s}) {
    if (records > back && !journal.saveSnapshot(session, records - back, map)) return false;
  }
  return true;
}

void takeover(int sessions, double minutes, Figures& f) {
  std::string why;
  auto cluster = testing::ClusterHarness::start(&why);
  if (!cluster) {
    std::fprintf(stderr, "takeover: cannot start PostgreSQL: %s\n", why.c_str());
    return;
  }
  // A real flight to repeat, and its map.
  cluster->startServer(kTakeoverDomain, "seed");
  cluster->startVehicle(kTakeoverDomain, 0, 300);
  if (!cluster->waitForVehicles(180s, &why)) {
    std::fprintf(stderr, "takeover: the seed flight failed: %s\n", why.c_str());
    return;
  }
  testing::waitUntil(60s, [&] {
    return cluster->server("seed").get("/api/sessions/flight0").body.find("\"fusion_backlog\":0") !=
           std::string::npos;
  });
  const std::string map = cluster->server("seed").get("/api/sessions/flight0/map.ot").body;
  const auto flight = testing::recordedFlight(*cluster, "flight0");
  cluster->takeServer("seed").reset();
  cluster->query("UPDATE sm_sessions SET state = 'closed', owner = NULL WHERE id = 'flight0'");
  if (flight.empty() || map.empty()) {
    std::fprintf(stderr, "takeover: no recorded flight\n");
    return;
  }
  // The history, written by a writer that then leaves the cluster (its sessions orphaned).
  const auto writing = Clock::now();
  {
    auto db = cluster::ClusterDb::open(
        {.url = cluster->db().url(), .server_id = "writer", .http = "127.0.0.1:1"});
    auto journal = cluster::ClusterJournal::open(cluster->db().url());
    if (!db || !journal) {
      std::fprintf(stderr, "takeover: cannot open the cluster\n");
      return;
    }
    for (int s = 0; s < sessions; ++s) {
      const std::string id = "history" + std::to_string(s);
      (void)(*db)->renewLease();  // writing takes seconds a session: the writer stays live
      auto placed = (*db)->placeSession(id, 0.1);
      auto adopted = placed ? (*db)->adopt(*placed) : placed;
      if (!adopted) {
        std::fprintf(stderr, "takeover: cannot place %s\n", id.c_str());
        return;
      }
      (*journal)->adopt(id, adopted->epoch, 0);
      if (!writeHistory(**journal, id, flight, map, minutes)) {
        std::fprintf(stderr, "takeover: cannot write %s's history\n", id.c_str());
        return;
      }
      std::fprintf(stderr, "takeover: %s: %.0f min of history written (%.0f s so far)\n",
                   id.c_str(), minutes, secondsSince(writing));
    }
    (void)(*db)->leave();
  }
  const std::string size =
      cluster->query("SELECT pg_size_pretty(pg_database_size(current_database()))");
  std::fprintf(stderr, "takeover: the database holds %s\n", firstLine(size).c_str());
  auto served = [&](const std::string& name) {
    return testing::seriesValue(cluster->server(name).get("/metrics").body,
                                "stereomap_cluster_sessions_served");
  };
  // The first owner takes them all (a fresh server: every session recovered from its history).
  const auto first = Clock::now();
  cluster->startServer(kTakeoverDomain, "victim");
  if (!testing::waitUntil(
          120s, [&] { return served("victim") == sessions; }, 100ms)) {
    const std::string log = cluster->server("victim").log();
    std::fprintf(stderr, "takeover: the first server did not serve them all:\n%s\n",
                 log.substr(log.size() > 3000 ? log.size() - 3000 : 0).c_str());
    return;
  }
  std::fprintf(stderr, "takeover: a fresh server took %d sessions in %.1f s\n", sessions,
               secondsSince(first));
  cluster->startServer(kTakeoverDomain, "survivor");
  std::this_thread::sleep_for(3s);
  cluster->server("victim").process().kill9();
  const auto killed = Clock::now();
  if (!testing::waitUntil(
          120s, [&] { return served("survivor") == sessions; }, 100ms)) {
    std::fprintf(stderr, "takeover: the survivor did not serve them all\n");
    return;
  }
  f.takeover_s = secondsSince(killed);
  f.history_min = minutes;
  std::fprintf(stderr,
               "takeover: %d sessions of %.0f min each served again %.1f s after their server "
               "was killed (lease 2 s)\n",
               sessions, minutes, f.takeover_s);
}

void control(int servers, int sessions, double seconds, Figures& f) {
  std::string why;
  auto cluster = testing::ClusterHarness::start(&why);
  if (!cluster) {
    std::fprintf(stderr, "control: cannot start PostgreSQL: %s\n", why.c_str());
    return;
  }
  // The production lease (4 s) and poll (250 ms).
  for (int i = 0; i < servers; ++i) {
    cluster->startServer(kControlDomain, "s" + std::to_string(i), 4);
  }
  // Sessions waiting for owners (as imported ones do): the servers share them out.
  cluster->query(
      "INSERT INTO sm_sessions (id, owner, epoch, resolution, state) SELECT 'c' || g, NULL, 1, "
      "0.1, 'live' FROM generate_series(1, " +
      std::to_string(sessions) + ") g");
  auto total = [&] {
    double sum = 0;
    for (auto& [name, server] : cluster->servers()) {
      sum +=
          testing::seriesValue(server->get("/metrics").body, "stereomap_cluster_sessions_served");
    }
    return sum;
  };
  const auto placing = Clock::now();
  if (!testing::waitUntil(
          600s, [&] { return total() >= sessions; }, 1s)) {
    std::fprintf(stderr, "control: only %.0f of %d sessions served\n", total(), sessions);
  }
  std::fprintf(stderr, "control: %.0f sessions served by %d servers after %.1f s\n", total(),
               servers, secondsSince(placing));
  std::this_thread::sleep_for(5s);
  auto statements = [&] {
    std::map<std::string, double> out;
    for (auto& [name, server] : cluster->servers()) {
      out[name] = testing::seriesValue(server->get("/metrics").body,
                                       "stereomap_cluster_control_statements_total");
    }
    return out;
  };
  auto commits = [&] {
    return std::stod(
        "0" + firstLine(cluster->query("SELECT xact_commit FROM pg_stat_database WHERE datname = "
                                       "current_database()")));
  };
  const auto before = statements();
  const double commits_before = commits();
  const auto window = Clock::now();
  std::this_thread::sleep_for(std::chrono::duration<double>(seconds));
  const double span = secondsSince(window);
  const auto after = statements();
  const double commits_after = commits();
  double worst = 0;
  for (const auto& [name, count] : after) {
    const double rate = (count - before.at(name)) / span;
    worst = std::max(worst, rate);
    std::fprintf(stderr, "control: server %s %.1f statements/s\n", name.c_str(), rate);
  }
  f.control_per_server = worst;
  std::fprintf(stderr,
               "control: %d servers, %d live sessions: at most %.1f control statements/s per "
               "server; the database committed %.1f transactions/s in all\n",
               servers, sessions, worst, (commits_after - commits_before) / span);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "stereomap-bench-chaos: the cluster under random faults for many minutes (servers "
      "killed, paused, restarted under their id; the database primary killed and hung; nginx "
      "restarted), every flight checked at the end; failover with long histories; the "
      "control plane's load"};
  ScheduleOptions o;
  std::string only = "schedule,takeover,control";
  int history_sessions = 16, control_servers = 8, control_sessions = 2000;
  double history_minutes = 30, control_seconds = 60;
  app.add_option("--minutes", o.minutes, "How long faults are drawn")->capture_default_str();
  app.add_option("--interval", o.interval_s, "Mean seconds between faults")->capture_default_str();
  app.add_option("--vehicles", o.vehicles, "Vehicles flying at once")->capture_default_str();
  app.add_option("--flight-frames", o.flight_frames, "Frames (at 10 Hz) of each flight")
      ->capture_default_str();
  app.add_option("--seed", o.seed, "The random schedule's seed")->capture_default_str();
  app.add_option("--history-sessions", history_sessions, "Sessions of the takeover")
      ->capture_default_str();
  app.add_option("--history-minutes", history_minutes, "Minutes of history of each")
      ->capture_default_str();
  app.add_option("--control-servers", control_servers, "Servers of the control phase")
      ->capture_default_str();
  app.add_option("--control-sessions", control_sessions, "Live sessions of the control phase")
      ->capture_default_str();
  app.add_option("--control-seconds", control_seconds, "The control phase's window")
      ->capture_default_str();
  app.add_option("--only", only, "Comma-separated phases: schedule,takeover,control")
      ->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  auto want = [&](const char* phase) { return only.find(phase) != std::string::npos; };
  Figures f;
  if (want("takeover")) takeover(history_sessions, history_minutes, f);
  if (want("control")) control(control_servers, control_sessions, control_seconds, f);
  if (want("schedule")) schedule(o, f);
  std::printf(
      "chaos: %.0f min, %d faults, %ld samples: lost %ld, duplicated %ld; longest ingest gap "
      "%.1f s; database failover %.1f s; takeover with %.0f min of history %.1f s; control "
      "queries %.1f/s per server\n",
      f.minutes, f.faults, f.samples, f.lost, f.duplicated, f.longest_gap_s, f.database_failover_s,
      f.history_min, f.takeover_s, f.control_per_server);
  return 0;
}
