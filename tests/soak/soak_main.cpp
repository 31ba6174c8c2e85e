// stereomap-soak (issue 17): a long run with everything at once, not in CI (tests/soak/run).
// Simulated vehicles stream to two sessions while WebSocket viewers watch, and the server is
// killed with SIGKILL at a fixed period and restarted on the same store. At the end:
//   - every frame the killed server had journaled (acknowledged) is still in the journal;
//   - every frame a vehicle sent is in its session's journal, or was in flight at a kill:
//     after the last frame journaled before that kill and before the first one the restarted
//     server journaled (by record order, not by clocks); none is left unexplained;
//   - every restart recovered what the killed server had acknowledged;
//   - the last server's RSS grew at most 10 % after its warm-up (the median of its flights'
//     last minute against that of the minute after warm-up, and 20 s after they ended);
//   - every viewer is connected at the end, and none stayed away longer than a restart.
// Prints the figures for docs/BENCHMARKS.md and exits 1 when a check fails.
#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <thread>
#include <variant>
#include <vector>

#include "common/cli.hpp"
#include "common/statistics.hpp"
#include "common/time.hpp"
#include "proto/journal/journal.hpp"
#include "tests/support/server_fixture.hpp"
#include "tests/support/websocket_client.hpp"

namespace {

using namespace stereomap;
using namespace stereomap::testing;
using namespace std::chrono_literals;
using Clock = std::chrono::steady_clock;
using nlohmann::json;

struct Options {
  double minutes = 30;
  double kill_every_minutes = 5;
  int vehicles = 4;
  int sessions = 2;
  int viewers = 5;
  double rate = 5;
  int domain = 96;
  std::string store;
};

std::string sessionName(int i) { return "soak-" + std::string(1, static_cast<char>('a' + i)); }

// A server's downtime: from its kill to the restarted server answering, in wall-clock ns.
struct Downtime {
  int64_t killed_ns = 0, ready_ns = 0;
};

// What a session's journal held when its server was killed: the newest record number, and
// per vehicle the frames (seqs) journaled.
struct AtKill {
  uint64_t last_number = 0;
  std::map<std::string, std::set<uint64_t>> frames;  // vehicle -> seqs
};

AtKill journaled(const std::filesystem::path& journal_path) {
  AtKill at;
  auto journal = proto::journal::readJournal(journal_path);
  if (!journal) return at;
  for (size_t i = 0; i < journal->records.size(); ++i) {
    at.last_number = std::max(at.last_number, journal->numbers[i]);
    if (const auto* f = std::get_if<proto::CloudFrameMsg>(&journal->records[i])) {
      at.frames[f->vehicle_id].insert(f->seq);
    }
  }
  return at;
}

int64_t rssKiB(pid_t pid) {
  std::ifstream status("/proc/" + std::to_string(pid) + "/status");
  std::string key;
  int64_t value = 0;
  while (status >> key) {
    if (key == "VmRSS:") return (status >> value) ? value : 0;
    status.ignore(256, '\n');
  }
  return 0;
}

// The server's live heap (jemalloc's stats.allocated, from /metrics); 0 when not reported.
int64_t heapAllocatedKiB(const ServerProcess& server) {
  const auto reply = server.get("/metrics");
  const std::string key = "\nstereomap_heap_allocated_bytes ";
  const auto at = reply.status == 200 ? reply.body.find(key) : std::string::npos;
  if (at == std::string::npos) return 0;
  return static_cast<int64_t>(std::strtod(reply.body.c_str() + at + key.size(), nullptr)) / 1024;
}

// The median RSS of `samples` (seconds into a server's life, KiB) in [from, to); 0 if none.
int64_t medianKiB(const std::vector<std::pair<double, int64_t>>& samples, double from, double to) {
  std::vector<int64_t> in;
  for (const auto& [t, kib] : samples)
    if (t >= from && t < to) in.push_back(kib);
  return common::median(std::move(in)).value_or(0);
}

json sessionStatus(const ServerProcess& server, const std::string& session) {
  const auto reply = server.get("/api/sessions/" + session);
  if (reply.status != 200) return json::object();
  return json::parse(reply.body, nullptr, false);
}

int64_t count(const json& status, const char* key) {
  return status.contains(key) && status[key].is_number() ? status[key].get<int64_t>() : 0;
}

// A viewer that says hello, subscribes to a session and asks for its tiles, and comes back
// whenever it loses the server: what it received and how long it was away.
class Viewer {
 public:
  Viewer(const std::atomic<int>& port, std::string session)
      : port_(port), session_(std::move(session)), thread_([this] { run(); }) {}
  ~Viewer() {
    stop_ = true;
    thread_.join();
  }
  struct Figures {
    uint64_t messages = 0, bytes = 0, connections = 0;
    double longest_away_s = 0;
    bool connected_at_end = false;
  };
  Figures figures() const {
    std::lock_guard lock(mutex_);
    Figures f = figures_;
    f.connected_at_end = connected_ && Clock::now() - last_message_ < 10s;
    return f;
  }

 private:
  // A viewer thread never ends the run: whatever goes wrong with a connection (an exception
  // included) is a lost connection, and the viewer connects again.
  void run() {
    while (!stop_) {
      try {
        watch();
      } catch (const std::exception&) {
        std::lock_guard lock(mutex_);
        connected_ = false;
      }
    }
  }
  void watch() {
    while (!stop_) {
      WebSocketClient client(port_.load());
      if (client.status() != 101 || !client.sendText(R"({"type": "hello", "protocol": 2})") ||
          !client.sendText(R"({"type": "subscribe", "session": ")" + session_ + R"("})") ||
          !client.sendText(
              R"({"type": "view", "id": 1, "eye": [0, 0, 2], "budget": 200000, "error": 1})")) {
        std::this_thread::sleep_for(200ms);
        continue;
      }
      {
        std::lock_guard lock(mutex_);
        ++figures_.connections;
        const double away = std::chrono::duration<double>(Clock::now() - away_since_).count();
        if (figures_.connections > 1)
          figures_.longest_away_s = std::max(figures_.longest_away_s, away);
        connected_ = true;
        last_message_ = Clock::now();
      }
      while (!stop_) {
        const auto message = client.read(1s);
        std::lock_guard lock(mutex_);
        if (message.kind == WsMessage::Kind::kText || message.kind == WsMessage::Kind::kBinary) {
          ++figures_.messages;
          figures_.bytes += message.payload.size();
          last_message_ = Clock::now();
          continue;
        }
        // Pushes come several times a second: a close, or 3 s of silence, is a lost server.
        if (message.kind == WsMessage::Kind::kClose || Clock::now() - last_message_ > 3s) {
          connected_ = false;
          away_since_ = last_message_;
          break;
        }
        std::this_thread::sleep_for(50ms);  // (a lost socket answers at once: no spinning)
      }
    }
  }

  const std::atomic<int>& port_;
  const std::string session_;
  std::atomic<bool> stop_{false};
  mutable std::mutex mutex_;
  Figures figures_;
  bool connected_ = false;
  Clock::time_point last_message_ = Clock::now();
  Clock::time_point away_since_ = Clock::now();
  std::thread thread_;
};

// Waits until every session shows at least the frames the killed server had acknowledged.
bool recovered(const ServerProcess& server, const std::map<std::string, int64_t>& acknowledged) {
  return waitUntil(
      180s,
      [&] {
        for (const auto& [session, frames] : acknowledged) {
          if (count(sessionStatus(server, session), "frames") < frames) return false;
        }
        return true;
      },
      500ms);
}

struct Accounting {
  int64_t sent = 0, journaled = 0, lost_at_kills = 0, unexplained = 0, acknowledged_lost = 0;
  std::vector<std::string> problems;
};

// Every frame the vehicle sent (seq 0..frames-1) is in the final journal, or was in flight at
// a kill: newer than every frame of the vehicle journaled before that kill, and older than
// the first one journaled after it. Every frame journaled at a kill is still there.
void account(const std::filesystem::path& journal_path, const std::string& vehicle, int64_t frames,
             const std::vector<AtKill>& kills, Accounting& out) {
  auto journal = proto::journal::readJournal(journal_path);
  if (!journal) {
    out.problems.push_back(journal.error().message);
    return;
  }
  std::set<uint64_t> seqs;
  std::vector<uint64_t> first_after(kills.size(), std::numeric_limits<uint64_t>::max());
  for (size_t i = 0; i < journal->records.size(); ++i) {
    const auto* f = std::get_if<proto::CloudFrameMsg>(&journal->records[i]);
    if (f == nullptr || f->vehicle_id != vehicle) continue;
    seqs.insert(f->seq);
    for (size_t k = 0; k < kills.size(); ++k) {
      if (journal->numbers[i] > kills[k].last_number) {
        first_after[k] = std::min(first_after[k], f->seq);
      }
    }
  }
  out.sent += frames;
  out.journaled += static_cast<int64_t>(seqs.size());
  for (const auto& kill : kills) {
    const auto at = kill.frames.find(vehicle);
    if (at == kill.frames.end()) continue;
    for (const uint64_t seq : at->second) out.acknowledged_lost += seqs.count(seq) == 0;
  }
  for (uint64_t seq = 0; seq < static_cast<uint64_t>(frames); ++seq) {
    if (seqs.count(seq)) continue;
    bool explained = false;
    for (size_t k = 0; k < kills.size() && !explained; ++k) {
      const auto at = kills[k].frames.find(vehicle);
      const bool after_last =
          at == kills[k].frames.end() || at->second.empty() || seq > *at->second.rbegin();
      explained = after_last && seq < first_after[k];
    }
    if (explained) {
      ++out.lost_at_kills;
    } else if (++out.unexplained <= 10) {
      out.problems.push_back(vehicle + " frame " + std::to_string(seq) +
                             " is missing, and was not in flight at a kill");
    }
  }
}

int run(const Options& o) {
  const std::string store = o.store.empty() ? makeTempDir("stereomap-soak-store") : o.store;
  const std::string logs = makeTempDir("stereomap-soak-logs");
  const auto frames = static_cast<int64_t>(o.minutes * 60 * o.rate);
  std::printf(
      "soak: %.1f min, %d vehicles in %d sessions at %.1f Hz, %d viewers, SIGKILL every "
      "%.1f min; store %s, logs %s\n",
      o.minutes, o.vehicles, o.sessions, o.rate, o.viewers, o.kill_every_minutes, store.c_str(),
      logs.c_str());
  std::fflush(stdout);

  // Recovery reads each journal whole before the server listens: minutes may pass.
  const auto start_within = std::chrono::seconds(300);
  auto server = std::make_unique<ServerProcess>(o.domain, std::vector<std::string>{}, store,
                                                /*require_healthy=*/true, start_within);
  std::atomic<int> port{server->port()};
  std::vector<std::unique_ptr<ChildProcess>> vehicles;
  for (int v = 0; v < o.vehicles; ++v) {
    vehicles.push_back(std::make_unique<ChildProcess>(
        onboardArgs(o.domain, sessionName(v % o.sessions), static_cast<int>(frames),
                    {"--rate", std::to_string(o.rate), "--vehicle", "v" + std::to_string(v + 1),
                     "--seed", std::to_string(v + 1), "--vo", "gt", "--map-resolution", "0.1",
                     "--wait-for-server", "60"}),  // thinned clouds (the default), every one sent
        logs + "/vehicle-" + std::to_string(v + 1) + ".log"));
  }
  std::vector<std::unique_ptr<Viewer>> viewers;
  for (int i = 0; i < o.viewers; ++i) {
    viewers.push_back(std::make_unique<Viewer>(port, sessionName(i % o.sessions)));
  }

  const auto start = Clock::now();
  const auto end = start + std::chrono::duration<double, std::ratio<60>>(o.minutes);
  const auto period = std::chrono::duration<double, std::ratio<60>>(o.kill_every_minutes);
  auto next_kill = start + period;
  std::vector<Downtime> downtimes;
  std::vector<AtKill> kills;  // per kill and session: kills[k * sessions + s]
  std::vector<double> recovery_s;
  int recoveries_failed = 0;
  auto life_start = start;
  // The last server's RSS every second while every vehicle flies (seconds into its life, KiB).
  // Its growth is the median of its last minute against that of the minute after its warm-up,
  // not two single samples: a frame's fusion or a viewer's burst of tiles moves RSS by a few
  // MiB for a second or two either way.
  std::vector<std::pair<double, int64_t>> life_rss;
  int64_t peak_rss = 0;
  int64_t warm_heap = 0, last_heap = 0;  // live data, to tell growth of it from the allocator's
  bool all_exited = false;
  while (!all_exited) {
    std::this_thread::sleep_for(1s);
    const auto now = Clock::now();
    const pid_t pid = server->process().pid();
    const int64_t rss = rssKiB(pid);
    peak_rss = std::max(peak_rss, rss);
    const double age_s = std::chrono::duration<double>(now - life_start).count();
    if (warm_heap == 0 && age_s > 60) warm_heap = last_heap = heapAllocatedKiB(*server);
    const bool all_flying =
        std::all_of(vehicles.begin(), vehicles.end(), [](auto& v) { return v->running(); });
    if (all_flying && rss > 0) life_rss.emplace_back(age_s, rss);
    all_exited =
        std::all_of(vehicles.begin(), vehicles.end(), [](auto& v) { return !v->running(); });
    // (No kill in the last 90 s: the last server must live past its warm-up.)
    if (now < next_kill || now + 90s > end) continue;
    next_kill += period;

    std::map<std::string, int64_t> acknowledged;
    for (int s = 0; s < o.sessions; ++s) {
      acknowledged[sessionName(s)] =
          count(sessionStatus(*server, sessionName(s)), "frames_received");
    }
    Downtime down{common::nowNs(), 0};
    server->process().kill9();
    server.reset();
    for (int s = 0; s < o.sessions; ++s) {
      kills.push_back(journaled(std::filesystem::path(store) / sessionName(s) / "journal.smj"));
    }
    server = std::make_unique<ServerProcess>(o.domain, std::vector<std::string>{}, store,
                                             /*require_healthy=*/true, start_within);
    down.ready_ns = common::nowNs();
    port = server->port();
    downtimes.push_back(down);
    const auto restarted = Clock::now();
    const bool ok = recovered(*server, acknowledged);
    recoveries_failed += !ok;
    recovery_s.push_back(std::chrono::duration<double>(Clock::now() - restarted).count());
    std::printf("soak: kill %zu at %.1f min: back in %.1f s, recovered %s in %.1f s\n",
                downtimes.size(),
                std::chrono::duration<double, std::ratio<60>>(restarted - start).count(),
                (down.ready_ns - down.killed_ns) / 1e9, ok ? "everything" : "NOT everything",
                recovery_s.back());
    std::fflush(stdout);
    life_start = Clock::now();
    life_rss.clear();
    peak_rss = 0;
    warm_heap = last_heap = 0;
  }
  if (warm_heap > 0) last_heap = heapAllocatedKiB(*server);
  const double last_s = life_rss.empty() ? 0.0 : life_rss.back().first;
  const int64_t warm_rss = medianKiB(life_rss, 60, 120);
  const int64_t flying_rss = medianKiB(life_rss, std::max(60.0, last_s - 60), last_s + 1);
  std::this_thread::sleep_for(5s);  // the viewers see the last pushes
  std::vector<Viewer::Figures> seen;
  for (const auto& viewer : viewers) seen.push_back(viewer->figures());
  viewers.clear();
  int vehicles_failed = 0;
  for (auto& v : vehicles) vehicles_failed += v->waitExit(10s).value_or(-1) != 0;
  // The flights' ends save their sessions (maps, trajectory files), which lifts RSS for a
  // while; 20 s after them, jemalloc has returned what that freed (10 s decay).
  std::this_thread::sleep_for(15s);
  const int64_t settled_rss = rssKiB(server->process().pid());
  server->process().stop();

  Accounting accounting;
  for (int v = 0; v < o.vehicles; ++v) {
    std::vector<AtKill> session_kills;
    for (size_t k = 0; k < downtimes.size(); ++k) {
      session_kills.push_back(kills[k * o.sessions + v % o.sessions]);
    }
    account(std::filesystem::path(store) / sessionName(v % o.sessions) / "journal.smj",
            "v" + std::to_string(v + 1), frames, session_kills, accounting);
  }
  const double minutes =
      std::chrono::duration<double, std::ratio<60>>(Clock::now() - start).count();
  const auto growthOf = [&](int64_t kib) {
    return warm_rss > 0 ? 100.0 * static_cast<double>(kib - warm_rss) / warm_rss : 0.0;
  };
  const double growth = growthOf(flying_rss), settled_growth = growthOf(settled_rss);
  double longest_away = 0;
  int connected = 0;
  uint64_t messages = 0;
  for (const auto& f : seen) {
    longest_away = std::max(longest_away, f.longest_away_s);
    connected += f.connected_at_end;
    messages += f.messages;
  }
  const auto [fastest, slowest] =
      recovery_s.empty() ? std::pair{0.0, 0.0}
                         : std::pair{*std::min_element(recovery_s.begin(), recovery_s.end()),
                                     *std::max_element(recovery_s.begin(), recovery_s.end())};
  std::printf(
      "soak: ran %.1f min; %zu kills, %zu of %zu restarts recovered everything acknowledged "
      "(%.1f-%.1f s)\n",
      minutes, downtimes.size(), downtimes.size() - recoveries_failed, downtimes.size(), fastest,
      slowest);
  std::printf(
      "soak: frames sent %lld, journaled %lld, in flight at a kill %lld, unexplained %lld; "
      "journaled before a kill but lost %lld; vehicles failed %d\n",
      static_cast<long long>(accounting.sent), static_cast<long long>(accounting.journaled),
      static_cast<long long>(accounting.lost_at_kills),
      static_cast<long long>(accounting.unexplained),
      static_cast<long long>(accounting.acknowledged_lost), vehicles_failed);
  std::printf(
      "soak: last server's RSS (median of a minute) %lld KiB after warm-up -> %lld KiB in the "
      "flights' last minute (%+.1f %%), flying %.1f min; %lld KiB 20 s after the flights ended "
      "(%+.1f %%); peak %lld KiB\n",
      static_cast<long long>(warm_rss), static_cast<long long>(flying_rss), growth, last_s / 60,
      static_cast<long long>(settled_rss), settled_growth, static_cast<long long>(peak_rss));
  if (warm_heap == 0 || last_heap == 0) {
    std::printf("soak: its live heap: not reported (a server without jemalloc?)\n");
  } else {
    std::printf("soak: its live heap (jemalloc) %lld KiB after warm-up -> %lld KiB (%+.1f %%)\n",
                static_cast<long long>(warm_heap), static_cast<long long>(last_heap),
                100.0 * (last_heap - warm_heap) / warm_heap);
  }
  std::printf("soak: viewers %d of %zu connected at the end, longest away %.1f s, %llu messages\n",
              connected, seen.size(), longest_away, static_cast<unsigned long long>(messages));
  for (const auto& problem : accounting.problems) std::printf("soak: %s\n", problem.c_str());
  double longest_down = 0;
  for (const auto& d : downtimes)
    longest_down = std::max(longest_down, (d.ready_ns - d.killed_ns) / 1e9);
  const bool pass = recoveries_failed == 0 && accounting.unexplained == 0 &&
                    accounting.acknowledged_lost == 0 && accounting.problems.empty() &&
                    vehicles_failed == 0 && warm_rss > 0 && growth <= 10.0 &&
                    settled_growth <= 10.0 && connected == static_cast<int>(seen.size()) &&
                    longest_away <= longest_down + 10.0;  // back within a restart (and a push)
  std::printf("soak: %s\n", pass ? "PASS" : "FAIL");
  std::error_code ec;
  if (o.store.empty() && pass) std::filesystem::remove_all(store, ec);
  if (pass) std::filesystem::remove_all(logs, ec);
  return pass ? 0 : 1;
}

}  // namespace

int main(int argc, char** argv) {
  Options o;
  CLI::App app{
      "stereomap-soak: vehicles, viewers and a server killed with SIGKILL at a period, "
      "for a long run (tests/soak/run); exits 1 when something was lost"};
  app.add_option("--minutes", o.minutes, "How long the vehicles fly")
      ->check(CLI::Range(1.0, 1440.0));
  app.add_option("--kill-every", o.kill_every_minutes, "Minutes between SIGKILLs of the server")
      ->check(CLI::Range(0.5, 1440.0));
  app.add_option("--vehicles", o.vehicles, "Simulated vehicles")->check(CLI::Range(1, 16));
  app.add_option("--sessions", o.sessions, "Sessions they share")->check(CLI::Range(1, 16));
  app.add_option("--viewers", o.viewers, "WebSocket viewers")->check(CLI::Range(0, 64));
  app.add_option("--rate", o.rate, "Frames per second per vehicle")->check(CLI::Range(0.5, 30.0));
  app.add_option("--domain", o.domain, "DDS domain id")->check(CLI::Range(0, 232));
  app.add_option("--store", o.store,
                 "Store directory (default: a temporary one, removed on success)");
  if (auto exit_code = common::parseCommandLine(app, argc, argv)) return *exit_code;
  try {
    return run(o);  // (its processes are stopped as it unwinds)
  } catch (const std::exception& e) {
    std::printf("soak: %s\nsoak: FAIL\n", e.what());
    return 1;
  }
}
