// stereomap-bench-journal: what reading a session's newest frames back from its journal costs
// on a long flight, as the fusion worker does for frames it deferred while its queue was full.
// A journal of --megabytes of cloud frames is written through the store (SessionJournals);
// then the newest --frames are read back, alternately:
//   mark:  from the open journal's nearest mark (what the server does now);
//   whole: from the start of the file (a SessionJournals that has not opened it: the old way).
//   stereomap-bench-journal [--megabytes N] [--frames K] [--runs R] [--dir DIR]
#include <spdlog/spdlog.h>
#include <CLI/CLI.hpp>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <vector>

#include "common/cli.hpp"
#include "server/store/session_journals.hpp"
#include "tests/bench/bench_support.hpp"

namespace {

using namespace stereomap;
namespace fs = std::filesystem;

proto::CloudFrameMsg frame(uint64_t seq, size_t payload_bytes) {
  proto::CloudFrameMsg f;
  f.vehicle_id = "uav";
  f.session_id = "flight";
  f.seq = seq;
  f.stamp_ns = 1'000'000'000 + static_cast<int64_t>(seq) * 100'000'000;
  f.max_range = 8;
  f.point_count = static_cast<uint32_t>(payload_bytes / 6);  // about what Draco gives
  f.payload.resize(payload_bytes);
  for (size_t i = 0; i < payload_bytes; ++i) f.payload[i] = static_cast<uint8_t>(i * 31 + seq);
  return f;
}

// Milliseconds to read frames (after, last] of the session, and how many came.
double timeRead(const store::SessionJournals& journals, uint64_t after, uint64_t last,
                size_t& frames) {
  frames = 0;
  const auto start = bench::Clock::now();
  const auto read = journals.forEachFrame("flight", after, last,
                                          [&](const proto::CloudFrameMsg&, uint64_t) { ++frames; });
  const double ms = bench::msSince(start);
  if (!read) spdlog::error("reading failed: {}", read.error().message);
  return ms;
}

}  // namespace

int main(int argc, char** argv) {
  size_t megabytes = 160;
  size_t newest = 10;
  int runs = 5;
  std::string dir;
  CLI::App app{"What reading a session's newest frames back from a long journal costs"};
  app.add_option("--megabytes", megabytes, "journal size to write")->check(CLI::Range(1, 100000));
  app.add_option("--frames", newest, "newest frames to read back")->check(CLI::Range(1, 10000));
  app.add_option("--runs", runs, "readings of each kind, alternately")->check(CLI::Range(1, 100));
  app.add_option("--dir", dir, "where to write the journal (default: a temporary folder)");
  if (const auto exit = common::parseCommandLine(app, argc, argv)) return *exit;

  const fs::path root = dir.empty() ? fs::temp_directory_path() /
                                          ("stereomap-bench-journal-" + std::to_string(::getpid()))
                                    : fs::path(dir);
  constexpr size_t kPayloadBytes = 80'000;  // a whole sim cloud, Draco-encoded
  const size_t count = std::max<size_t>(newest + 1, megabytes * 1'000'000 / kPayloadBytes);
  store::SessionJournals journals(root, 0.1);
  uint64_t last = 0;
  for (size_t i = 0; i < count; ++i) {
    auto appended = journals.append(frame(i, kPayloadBytes));
    if (!appended) {
      std::fprintf(stderr, "bench-journal: %s\n", appended.error().message.c_str());
      return 1;
    }
    last = *appended;
  }
  std::printf("journal: %zu frames, %.0f MB in %s\n", count,
              static_cast<double>(fs::file_size(root / "flight" / store::kJournalName)) / 1e6,
              root.c_str());
  const store::SessionJournals unopened(root, 0.1);
  std::vector<double> mark_ms, whole_ms;
  for (int run = 0; run < runs; ++run) {
    size_t from_mark = 0, from_start = 0;
    mark_ms.push_back(timeRead(journals, last - newest, last, from_mark));
    whole_ms.push_back(timeRead(unopened, last - newest, last, from_start));
    if (from_mark != newest || from_start != newest) {
      std::fprintf(stderr, "bench-journal: read %zu and %zu frames, expected %zu\n", from_mark,
                   from_start, newest);
      return 1;
    }
  }
  const auto [mark_min, mark_max] = std::minmax_element(mark_ms.begin(), mark_ms.end());
  const auto [whole_min, whole_max] = std::minmax_element(whole_ms.begin(), whole_ms.end());
  std::printf(
      "newest %zu frames, %d runs each: from the mark %.1f-%.1f ms, whole file %.0f-%.0f ms\n",
      newest, runs, *mark_min, *mark_max, *whole_min, *whole_max);
  if (dir.empty()) fs::remove_all(root);
  return 0;
}
