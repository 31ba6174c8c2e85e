// stereomap-bench-outage (issue 38): nothing lost through an outage of any length, and a vehicle
// that falls behind stays live. Real stereomap-server and stereomap-onboard processes on
// loopback DDS:
//   - outage: a sim flight (typical camera, thinned clouds, --link-budget 1Mbit, ground-truth
//     poses), the server killed with SIGKILL `--at` seconds in and started again on the same
//     store `--down` seconds later; every pose and cloud the vehicle sent must be in the
//     session's journal, once; how long the vehicle took to catch up after the server's return
//     (its log), and the live poses' age at the server meanwhile (/metrics, p95 of the last 100).
//   - overload: the vehicle run at twice the frame rate its pipeline holds (measured first); the
//     age of its poses at the server.
//   - restart: the vehicle killed (SIGKILL) during an outage and started again on its spool; every
//     sample the first process sent must be journaled.
//   - spool: bytes the spool writes per minute of flight, thinned and whole clouds.
// The last line is the issue's figure line. --series FILE: the outage's flight second by second
// as CSV (FlightSeries), for scripts/plot-benchmarks.
//
//   stereomap-bench-outage [--down 60] [--flight 180] [--at 60] [--only outage,overload,...]
//                          [--secured] [--series FILE]
#include <spdlog/fmt/fmt.h>
#include <CLI/CLI.hpp>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <optional>
#include <sstream>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "proto/dds.hpp"
#include "tests/support/secure_deployment.hpp"
#include "tests/support/server_fixture.hpp"
#include "tests/support/stream_count.hpp"

namespace {

using namespace stereomap;
using namespace std::chrono_literals;
namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

constexpr int kDomain = 97;
const std::string kSession = "outage";

// The vehicle's pose age at the server, p95 of its last 100 poses (s), or nullopt.
std::optional<double> poseAgeP95(const testing::ServerProcess& server) {
  const auto reply = server.get("/metrics");
  if (reply.status != 200) return std::nullopt;
  std::istringstream lines(reply.body);
  std::string line;
  while (std::getline(lines, line)) {
    if (line.rfind("stereomap_vehicle_pose_latency_seconds{", 0) != 0) continue;
    if (line.find("quantile=\"0.95\"") == std::string::npos) continue;
    if (line.find("session=\"" + kSession + "\"") == std::string::npos) continue;
    return std::stod(line.substr(line.rfind(' ') + 1));
  }
  return std::nullopt;
}

// --secured: a deployment made by stereomap-certs, the server and vehicle sim-1 in it.
std::optional<testing::Deployment> g_deployment;

std::vector<std::string> serverArgs() {
  if (!g_deployment) return {};
  return {"--security", g_deployment->server()};
}

std::vector<std::string> vehicleArgs(int frames, double rate, const std::string& spool,
                                     const std::vector<std::string>& extra = {}) {
  std::vector<std::string> argv = {std::string(STEREOMAP_BIN_DIR) + "/stereomap-onboard",
                                   "--source",
                                   "sim",
                                   "--camera",
                                   "typical",
                                   "--session",
                                   kSession,
                                   "--frames",
                                   std::to_string(frames),
                                   "--rate",
                                   std::to_string(rate),
                                   "--spool",
                                   spool,
                                   "--dds-config",
                                   STEREOMAP_DDS_CONFIG,
                                   "--domain",
                                   std::to_string(kDomain),
                                   "--flush-timeout",
                                   "120"};
  if (g_deployment) {
    argv.insert(argv.end(), {"--vehicle", "sim-1", "--security", g_deployment->vehicle("sim-1")});
  }
  argv.insert(argv.end(), extra.begin(), extra.end());
  return argv;
}

// The outage's flight second by second: the vehicle's own counters (its once-a-second
// VehicleStatus, read here on DDS as a server reads it, so they go on through the outage) and
// the poses the server holds while it is up. Empty cells: not known that second. Without
// --secured only: the bench's participant has no identity in a secured domain.
class FlightSeries {
 public:
  explicit FlightSeries(const std::string& path) : out_(path), start_(Clock::now()) {
    if (!out_) throw std::runtime_error("cannot write " + path);
    out_ << "seconds,server_up,vehicle_frames,spool_samples,spool_bytes,server_poses,"
            "pose_age_p95_ms\n";
    auto participant =
        proto::Participant::create({.domain_id = kDomain, .config_file = STEREOMAP_DDS_CONFIG});
    if (!participant) return;
    participant_ = *participant;
    auto reader = proto::Reader<proto::VehicleStatusMsg>::create(participant_,
                                                                 {proto::kEverySessionPartition});
    if (reader) reader_ = std::move(reader).value();
  }
  // A row for now; `server` is null while it is away, `age_ms` the live poses' age p95.
  void sample(const testing::ServerProcess* server, std::optional<double> age_ms) {
    std::vector<proto::VehicleStatusMsg> statuses;
    if (reader_) reader_->take(statuses, std::chrono::milliseconds(0));
    for (const auto& status : statuses) {
      if (!latest_ || status.stamp_ns > latest_->stamp_ns) latest_ = status;
    }
    out_ << fmt::format("{:.1f},{:d},",
                        std::chrono::duration<double>(Clock::now() - start_).count(),
                        server != nullptr);
    if (latest_) {
      out_ << fmt::format("{},{},{},", latest_->frames, latest_->spool_samples,
                          latest_->spool_bytes);
    } else {
      out_ << ",,,";
    }
    const double poses = server ? testing::numberIn(server->get("/api/sessions/" + kSession).body,
                                                    R"("poses":([0-9]+))")
                                : -1;
    if (poses >= 0) out_ << fmt::format("{:.0f}", poses);
    out_ << ',';
    if (age_ms) out_ << fmt::format("{:.0f}", *age_ms);
    out_ << '\n' << std::flush;
  }

 private:
  std::ofstream out_;
  Clock::time_point start_;
  std::shared_ptr<proto::Participant> participant_;
  std::unique_ptr<proto::Reader<proto::VehicleStatusMsg>> reader_;
  std::optional<proto::VehicleStatusMsg> latest_;
};

struct OutageRun {
  double down_s = 0;
  size_t poses = 0, poses_sent = 0, clouds = 0, clouds_sent = 0, repeated = 0, duplicates = 0;
  double catch_up_s = -1;
  double live_age_p95_ms = -1;  // the largest p95 read during the catch-up
  double spool_mib = 0, flight_s = 0;
};

// One flight with the server away `down_s` seconds from `at_s` on; `series`, when given, gets
// a row a second until the vehicle is done.
OutageRun outage(double flight_s, double at_s, double down_s,
                 const std::vector<std::string>& extra = {}, const std::string& label = "",
                 FlightSeries* series = nullptr) {
  OutageRun run{.down_s = down_s, .flight_s = flight_s};
  const std::string store = testing::makeTempDir("stereomap-outage-store");
  const std::string spool = store + ".spool";
  const std::string vehicle_log = store + ".vehicle.log";
  auto server = std::make_unique<testing::ServerProcess>(kDomain, serverArgs(), store);
  testing::ChildProcess vehicle(vehicleArgs(static_cast<int>(flight_s * 10), 10, spool, extra),
                                vehicle_log);
  // The live poses' age p95 at the server (ms), while it is up and has one.
  auto live_age_ms = [&]() -> std::optional<double> {
    const auto age = server ? poseAgeP95(*server) : std::nullopt;
    return age ? std::optional(*age * 1000) : std::nullopt;
  };
  // Waits `seconds`, a row of the series a second meanwhile.
  auto wait = [&](double seconds) {
    const auto end = Clock::now() + std::chrono::duration<double>(seconds);
    for (auto next = Clock::now(); next < end; next += 1s) {
      std::this_thread::sleep_until(next);
      if (series) series->sample(server.get(), live_age_ms());
    }
    std::this_thread::sleep_until(end);
  };
  if (down_s > 0) {
    wait(at_s);
    server->process().kill9();
    server.reset();
    wait(down_s);
    server = std::make_unique<testing::ServerProcess>(kDomain, serverArgs(), store, true, 120s);
  }
  // Live poses' age while the vehicle catches up (it says when it has); the series goes on to
  // the flight's end.
  while (vehicle.running()) {
    const bool caught_up =
        testing::readText(vehicle_log).find("link: caught up") != std::string::npos;
    if (caught_up && !series) break;
    const auto age_ms = live_age_ms();
    if (age_ms && !caught_up) {
      run.live_age_p95_ms = std::max(run.live_age_p95_ms, *age_ms);
      std::fprintf(stderr, "catching up: live pose age p95 %.0f ms\n", *age_ms);
    }
    if (series) series->sample(server.get(), age_ms);
    std::this_thread::sleep_for(1s);
  }
  const auto code = vehicle.waitExit(std::chrono::seconds(static_cast<int>(flight_s) + 300));
  const std::string log = testing::readText(vehicle_log);
  if (!code || *code != 0)
    std::fprintf(stderr, "the vehicle failed; its log: %s\n", vehicle_log.c_str());
  run.catch_up_s = testing::numberIn(log, R"(caught up ([0-9.]+) s after the server came back)");
  const testing::Sent sent = testing::sentBy(log);
  run.poses_sent = sent.poses;
  run.clouds_sent = sent.clouds;
  run.spool_mib = testing::numberIn(log, R"(([0-9]+) KiB written to disk)") / 1024;
  // Samples the server received again (DDS history, spool) after its restart.
  const std::string metrics = server->get("/metrics").body;
  for (const char* topic : {"Pose", "CloudFrame", "SessionEvent", "PoseCorrection"}) {
    run.duplicates += static_cast<size_t>(testing::seriesValue(
        metrics, std::string("stereomap_samples_duplicate_total{topic=\"") + topic + "\"}"));
  }
  server->process().stop();
  server.reset();
  const auto found = testing::journaledSamples(store, kSession);
  run.poses = found.poseCount();
  run.clouds = found.cloudCount();
  run.repeated = found.repeated;
  const std::string first =
      label.empty() ? fmt::format("{:.0f} s at {:.0f} s of {:.0f} s", down_s, at_s, flight_s)
                    : label;
  std::printf("| %s | %zu / %zu | %zu / %zu | %zu | %zu | %.1f | %.0f | %.1f |\n", first.c_str(),
              run.poses, run.poses_sent, run.clouds, run.clouds_sent, run.repeated, run.duplicates,
              run.catch_up_s, run.live_age_p95_ms, run.spool_mib / flight_s * 60);
  std::fflush(stdout);
  fs::remove_all(store);
  fs::remove_all(spool);
  fs::remove(vehicle_log);
  return run;
}

// The frame rate the vehicle's pipeline holds (frames per second with --rate 0).
double sustainableRate(const std::vector<std::string>& extra) {
  const std::string dir = testing::makeTempDir("stereomap-outage-rate");
  // Published to no one (a domain of its own): the whole frame's work, as in flight.
  auto argv = vehicleArgs(60, 0, "off", extra);
  for (const auto& [flag, value] : {std::pair{"--domain", "230"}, {"--flush-timeout", "0"}}) {
    *(std::find(argv.begin(), argv.end(), flag) + 1) = value;
  }
  argv.insert(argv.end(), {"--wait-for-server", "0"});
  const auto run = testing::runTool(argv, 300s);
  const double frame_ms = testing::numberIn(run.output, R"(frame ([0-9.]+) ms \(medians\))");
  fs::remove_all(dir);
  return frame_ms > 0 ? 1000 / frame_ms : 0;
}

// The vehicle at twice its sustainable rate: the age of its poses at the server (p95, ms),
// the largest read over the flight after its first 10 s.
double overloaded(double seconds) {
  const std::vector<std::string> odometry = {"--vo", "fast"};
  const double rate = 2 * sustainableRate(odometry);
  const std::string store = testing::makeTempDir("stereomap-overload-store");
  testing::ServerProcess server(kDomain, serverArgs(), store);
  const std::string log_path = store + ".vehicle.log";
  testing::ChildProcess vehicle(
      vehicleArgs(static_cast<int>(seconds * rate), rate, "memory", odometry), log_path);
  double worst = -1;
  const auto start = Clock::now();
  while (vehicle.running()) {
    std::this_thread::sleep_for(1s);
    if (Clock::now() - start < 10s) continue;
    if (const auto age = poseAgeP95(server)) worst = std::max(worst, *age * 1000);
  }
  const std::string log = testing::readText(log_path);
  std::printf("| %.1f Hz (twice the %.1f it holds) | %.0f | %.0f of %.0f |\n", rate, rate / 2,
              worst, testing::numberIn(log, R"(([0-9]+) frames skipped to stay live)"),
              seconds * rate);
  fs::remove(log_path);
  return worst;
}

// The vehicle killed during an outage and started again on its spool: every sample the first
// process sent is journaled (the spool's files say how far it went).
void restart() {
  const std::string store = testing::makeTempDir("stereomap-restart-store");
  const std::string spool = store + ".spool";
  auto server = std::make_unique<testing::ServerProcess>(kDomain, serverArgs(), store);
  {
    testing::ChildProcess first(vehicleArgs(600, 10, spool), store + ".first.log");
    std::this_thread::sleep_for(20s);
    server->process().kill9();
    server.reset();
    std::this_thread::sleep_for(15s);
    first.kill9();
  }
  // How far the first process went (its spool's files say).
  const auto reach = testing::spooledReach(spool);
  server = std::make_unique<testing::ServerProcess>(kDomain, serverArgs(), store);
  testing::ChildProcess second(vehicleArgs(300, 10, spool), store + ".second.log");
  second.waitExit(300s);
  server->process().stop();
  server.reset();
  const auto found = testing::journaledSamples(store, kSession);
  for (const auto& [stream, sent] : reach) {
    std::printf("| the first process (stream %016llx) | %zu / %llu poses, %zu / %llu clouds |\n",
                static_cast<unsigned long long>(stream), found.poseCount(stream),
                static_cast<unsigned long long>(sent.poses), found.cloudCount(stream),
                static_cast<unsigned long long>(sent.clouds));
  }
  fs::remove_all(store);
  fs::remove_all(spool);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"stereomap-bench-outage: nothing lost through a server outage (issue 38)"};
  double down_s = 60, flight_s = 180, at_s = 60;
  std::vector<std::string> only = {"outage", "overload", "restart", "spool"};
  app.add_option("--down", down_s, "Seconds the server is away")->capture_default_str();
  app.add_option("--flight", flight_s, "Seconds of flight at 10 Hz")->capture_default_str();
  app.add_option("--at", at_s, "Seconds into the flight the server is killed")
      ->capture_default_str();
  app.add_option("--only", only, "Parts to run, comma-separated")
      ->delimiter(',')
      ->check(CLI::IsMember({"outage", "overload", "restart", "spool"}));
  bool secured = false;
  app.add_flag("--secured", secured,
               "Server and vehicle with DDS Security (a deployment made by stereomap-certs)");
  std::string series_path;
  app.add_option("--series", series_path,
                 "Write the outage's flight second by second to this CSV file")
      ->excludes("--secured");
  CLI11_PARSE(app, argc, argv);
  if (secured) {
    g_deployment = testing::makeDeployment({"sim-1"});
    if (!g_deployment->ok) {
      std::fprintf(stderr, "stereomap-certs failed:\n%s\n", g_deployment->log.c_str());
      return 1;
    }
    std::printf("Secured: DDS Security on the server and the vehicle (%s)\n\n",
                g_deployment->dir.c_str());
  }
  auto wanted = [&](const char* part) {
    return std::find(only.begin(), only.end(), part) != only.end();
  };
  if (at_s + 10 > flight_s) {
    std::fprintf(stderr, "--at must leave at least 10 s of flight\n");
    return 2;
  }

  std::optional<OutageRun> main_run;
  if (wanted("outage")) {
    std::printf(
        "## Outage: server killed and started again (typical camera, thinned clouds, 1 Mbit/s)\n\n"
        "| server down | poses journaled / sent | clouds journaled / sent | records repeated | "
        "received again | caught up (s) | live pose age p95 during catch-up (ms) | spool MB per "
        "minute |\n"
        "|---|---|---|---|---|---|---|---|\n");
    std::optional<FlightSeries> series;
    try {
      if (!series_path.empty()) series.emplace(series_path);
    } catch (const std::exception& e) {
      std::fprintf(stderr, "--series: %s\n", e.what());
      return 1;
    }
    main_run = outage(flight_s, at_s, down_s, {}, "", series ? &*series : nullptr);
  }
  if (wanted("spool")) {
    std::printf(
        "\n## Spool bytes per minute of flight (server up, 60 s)\n\n"
        "| clouds | poses journaled / sent | clouds journaled / sent | records repeated | "
        "received again | caught up (s) | live pose age p95 (ms) | spool MB per minute |\n"
        "|---|---|---|---|---|---|---|---|\n");
    outage(60, 0, 0, {}, "thinned (the default)");
    outage(60, 0, 0, {"--map-resolution", "0", "--link-budget", "off"},
           "whole (`--map-resolution 0 --link-budget off`)");
  }
  double overload_p95 = -1;
  if (wanted("overload")) {
    std::printf(
        "\n## Overloaded vehicle (fast odometry, sim at twice what it holds, 30 s)\n\n"
        "| rate | pose age p95 at the server (ms) | frames skipped |\n|---|---|---|\n");
    overload_p95 = overloaded(30);
  }
  if (wanted("restart")) {
    std::printf(
        "\n## Vehicle killed during an outage, started again on its spool\n\n"
        "| samples of | journaled / sent |\n|---|---|\n");
    restart();
  }
  if (main_run && overload_p95 >= 0) {
    std::printf(
        "\noutage: %.0f s down: %zu/%zu poses, %zu/%zu clouds journaled, caught up in %.1f s; live "
        "pose age p95 %.0f ms during catch-up; overloaded vehicle pose age p95 %.0f ms\n",
        main_run->down_s, main_run->poses, main_run->poses_sent, main_run->clouds,
        main_run->clouds_sent, main_run->catch_up_s, main_run->live_age_p95_ms, overload_p95);
  }
  if (g_deployment) std::filesystem::remove_all(g_deployment->dir);
  return 0;
}
