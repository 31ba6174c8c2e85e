// stereomap-bench-interop: what opening a session in Foxglove's tools costs (issue 42). A sim
// flight of --minutes into a real stereomap-server's store, then `stereomap-store export
// --mcap` of it: the time, the file's size per minute of flight, and the export's peak
// resident memory beyond what replaying the session alone takes (`stereomap-store show`).
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

constexpr int kDomain = 112;

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
  std::printf("mcap: %.1f s to export %.1f min of flight, %.1f MB, peak RSS +%.0f MB\n",
              exported.seconds, minutes, mb, exported.peak_rss_mb - replay.peak_rss_mb);
  std::filesystem::remove_all(dir);
  return 0;
}
