// stereomap-bench-interop: what opening a session in Foxglove's tools costs (issue 42). A sim
// flight of --minutes into a real stereomap-server's store, then `stereomap-store export
// --mcap` of it: the time, the file's size per minute of flight, and the export's peak
// resident memory beyond what replaying the session alone takes (`stereomap-store show`); the
// campus map (fr_campus.bt) exported likewise. Then Foxglove's own client, live
// (tests/interop/foxglove_bench.mjs, in Node): the lag of map messages at --viewers clients
// while a vehicle flies in real time, and a new client's wait for the campus map.
#include <fcntl.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include <chrono>
#include <cstdio>
#include <filesystem>

#include "common/cli.hpp"
#include "tests/support/process.hpp"
#include "tests/support/server_fixture.hpp"

using namespace stereomap;
using namespace stereomap::testing;

namespace {

constexpr int kDomain = 112, kFoxgloveDomain = 114;

struct Measured {
  int exit_code = -1;
  double seconds = 0, peak_rss_mb = 0;
};

// Runs argv to its end: its time and peak resident memory (the kernel's, from wait4).
Measured measure(const std::vector<std::string>& argv) {
  const auto start = std::chrono::steady_clock::now();
  const pid_t pid = ::fork();
  if (pid == 0) {
    std::vector<char*> args;
    for (const auto& a : argv) args.push_back(const_cast<char*>(a.c_str()));
    args.push_back(nullptr);
    const int null = ::open("/dev/null", O_WRONLY);
    ::dup2(null, STDOUT_FILENO);
    ::execv(args[0], args.data());
    ::_exit(127);
  }
  Measured m;
  int status = 0;
  rusage usage{};
  ::wait4(pid, &status, 0, &usage);
  m.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  m.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  m.peak_rss_mb = usage.ru_maxrss / 1024.0;  // kilobytes on Linux
  return m;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"stereomap-bench-interop: a session's MCAP export (size, time, memory)"};
  double minutes = 2;
  bool whole = false;
  app.add_option("--minutes", minutes, "Minutes of sim flight at 10 Hz")
      ->check(CLI::Range(0.1, 120.0))
      ->capture_default_str();
  app.add_flag("--whole-clouds", whole,
               "Every cloud sent whole, as the tests fly (the worst case); default: the "
               "vehicle's own defaults (clouds thinned to the map, skipped when nothing is new, "
               "1 Mbit/s)");
  int viewers = 10;
  double live_seconds = 60;
  app.add_option("--viewers", viewers, "Foxglove clients on the live session (0: no live part)")
      ->check(CLI::Range(0, 100))
      ->capture_default_str();
  app.add_option("--live-seconds", live_seconds, "Seconds of the live flight they watch")
      ->check(CLI::Range(5.0, 3600.0))
      ->capture_default_str();
  if (auto exit_code = common::parseCommandLine(app, argc, argv)) return *exit_code;

  const std::string dir = makeTempDir("stereomap-bench-interop");
  const std::string store = dir + "/store", mcap = dir + "/flight.mcap";
  const int frames = static_cast<int>(minutes * 600);
  {
    ServerProcess server(kDomain, {}, store);
    std::printf("flying %d frames (%.1f min at 10 Hz) into %s...\n", frames, minutes,
                store.c_str());
    std::fflush(stdout);
    std::vector<std::string> flags = {"--rate", "0"};
    if (!whole) {  // onboardArgs' test defaults give way to the vehicle's own
      flags.insert(flags.end(),
                   {"--min-new", "0.1", "--map-resolution", "0.1", "--link-budget", "1Mbit"});
    }
    ChildProcess onboard(onboardArgs(kDomain, "flight", frames, flags), dir + "/onboard.log");
    if (auto code = onboard.waitExit(std::chrono::hours(3)); !code || *code != 0) {
      std::fprintf(stderr, "the vehicle failed; its log: %s/onboard.log\n", dir.c_str());
      return 1;
    }
    waitUntil(std::chrono::minutes(10), [&] {
      const auto reply = server.get("/api/sessions/flight");
      if (reply.status != 200) return false;
      const auto status = nlohmann::json::parse(reply.body);
      return status["fusion_backlog"] == 0;
    });
    server.process().stop();
  }
  const std::string tool = std::string(STEREOMAP_BIN_DIR) + "/stereomap-store";
  const Measured replay = measure({tool, "--store", store, "show", "flight"});
  const Measured exported = measure({tool, "--store", store, "export", "flight", "--mcap", mcap});
  if (replay.exit_code != 0 || exported.exit_code != 0) {
    std::fprintf(stderr, "stereomap-store failed (show %d, export %d)\n", replay.exit_code,
                 exported.exit_code);
    return 1;
  }
  const double mb = static_cast<double>(std::filesystem::file_size(mcap)) / 1e6;
  std::printf(
      "\n| flight | MCAP | per minute of flight | export | replay alone: peak RSS | "
      "export: peak RSS |\n|---|---|---|---|---|---|\n");
  std::printf(
      "| %.1f min, %d frames | %.1f MB | %.1f MB | %.2f s (%.0fx faster than the flight) "
      "| %.0f MB | %.0f MB |\n\n",
      minutes, frames, mb, mb / minutes, exported.seconds, minutes * 60 / exported.seconds,
      replay.peak_rss_mb, exported.peak_rss_mb);
  // The campus map: MCAP bytes per map (its export writes the map's tiles and map.bt).
  const std::string campus = std::string(STEREOMAP_DATA_DIR) + "/octomap_samples/fr_campus.bt";
  if (std::filesystem::exists(campus)) {
    const std::string campus_mcap = dir + "/campus.mcap";
    const Measured imported =
        measure({tool, "--store", store, "import", campus, "--session", "campus"});
    const Measured campus_export =
        measure({tool, "--store", store, "export", "campus", "--mcap", campus_mcap});
    if (imported.exit_code == 0 && campus_export.exit_code == 0) {
      std::printf(
          "campus map (fr_campus.bt) as MCAP: %.1f MB, exported in %.2f s, peak RSS %.0f MB\n\n",
          static_cast<double>(std::filesystem::file_size(campus_mcap)) / 1e6, campus_export.seconds,
          campus_export.peak_rss_mb);
    }
  } else {
    std::printf("campus map skipped: %s is absent\n\n", campus.c_str());
  }

  double live_p95 = -1;
  if (viewers > 0) {
    const std::string command =
        std::string(STEREOMAP_NODE) + " " + STEREOMAP_FOXGLOVE_BENCH + " --bin-dir " +
        STEREOMAP_BIN_DIR + " --dds-config " + STEREOMAP_DDS_CONFIG + " --domain " +
        std::to_string(kFoxgloveDomain) + " --viewers " + std::to_string(viewers) + " --seconds " +
        std::to_string(live_seconds) + " --campus " + campus;
    std::printf("Foxglove clients: %s\n", command.c_str());
    std::fflush(stdout);
    std::string last;
    if (FILE* out = ::popen(command.c_str(), "r")) {
      char line[65536];
      while (std::fgets(line, sizeof line, out)) last = line;
      if (::pclose(out) != 0) last.clear();
    }
    const auto figures = nlohmann::json::parse(last, nullptr, false);
    if (figures.is_discarded() || !figures.contains("live")) {
      std::fprintf(stderr, "the Foxglove clients failed (see above)\n");
      return 1;
    }
    const auto& live = figures["live"];
    live_p95 = live["lag_p95_ms"].get<double>();
    std::printf(
        "\n| Foxglove clients | live map messages | lag p50 | lag p95 | lag max | all messages |\n"
        "|---|---|---|---|---|---|\n| %d, %.0f s of flight | %d | %.0f ms | %.0f ms | %.0f ms | "
        "%d, %.1f MB |\n\n",
        viewers, live_seconds, live["map_messages"].get<int>(), live["lag_p50_ms"].get<double>(),
        live_p95, live["lag_max_ms"].get<double>(), live["messages"].get<int>(),
        live["mb"].get<double>());
    if (figures.contains("campus")) {
      std::printf(
          "| campus map to a new Foxglove client | first map message | whole map | "
          "entities | cubes | bytes |\n|---|---|---|---|---|---|\n");
      for (const auto& run : figures["campus"]["runs"]) {
        std::printf("| %d voxels | %.0f ms | %.0f ms | %d | %d | %.1f MB |\n",
                    figures["campus"]["voxels"].get<int>(), run["first_ms"].get<double>(),
                    run["all_ms"].get<double>(), run["entities"].get<int>(),
                    run["cubes"].get<int>(), run["bytes"].get<double>() / 1e6);
      }
      std::printf("\n");
    }
  }
  std::printf(
      "mcap: %.1f s to export %.1f min of flight, %.1f MB, peak RSS +%.0f MB; foxglove "
      "live p95 %.0f ms\n",
      exported.seconds, minutes, mb, exported.peak_rss_mb - replay.peak_rss_mb, live_p95);
  std::filesystem::remove_all(dir);
  return 0;
}
