// stereomap-bench-trajectory: what a long flight's trajectory costs the server when viewers
// subscribe to it, and when a pose correction moves it (every pose is sent again). A session
// of --vehicles x --poses (default 4 x 54,000: three hours at 5 Hz) in a MapServer, and
// --viewers ViewerHub viewers, run as the network thread runs them:
//   subscribe:  every viewer subscribes; the time the hub took (the network thread is blocked
//               for it) and the live heap it left (jemalloc's, as the server's /metrics);
//   drain:      every message taken and "written", a message of each viewer in turn (as the
//               network thread writes to its connections): time, the longest single next()
//               (what one message costs the network thread), bytes, and the live heap's peak
//               above what it was before the subscribes;
//   correction: one correction of one vehicle, a poll, then the drain again; viewers closed
//               (a viewer whose unsent messages pass the hub's 4 MiB cap is closed).
//   stereomap-bench-trajectory [--poses N] [--vehicles V] [--viewers W]
#include <CLI/CLI.hpp>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include "common/cli.hpp"
#include "common/heap.hpp"
#include "server/viewers/viewer_hub.hpp"
#include "tests/bench/bench_support.hpp"

namespace {

using namespace stereomap;

double liveMegabytes() {
  const auto heap = common::heapStats();
  return heap ? static_cast<double>(heap->allocated) / (1 << 20) : 0.0;
}

struct Drained {
  double ms = 0, longest_ms = 0, megabytes = 0, peak_live_mb = 0;
  size_t messages = 0, closed = 0;
};

// Takes every viewer's messages as the network thread would write them: one of each viewer in
// turn while any has one.
Drained drain(viewers::ViewerHub& hub, const std::vector<viewers::ViewerHub::Id>& ids) {
  Drained d;
  d.peak_live_mb = liveMegabytes();
  for (const auto id : ids) d.closed += hub.closing(id).has_value();
  const auto start = bench::Clock::now();
  for (bool any = true; any;) {
    any = false;
    for (const auto id : ids) {
      if (hub.closing(id)) continue;
      const auto one = bench::Clock::now();
      const auto message = hub.next(id, common::nowNs());
      d.longest_ms = std::max(d.longest_ms, bench::msSince(one));
      if (!message) continue;
      any = true;
      d.megabytes += static_cast<double>(message->bytes->size()) / (1 << 20);
      if (++d.messages % 4 == 0) d.peak_live_mb = std::max(d.peak_live_mb, liveMegabytes());
      hub.written(id);
    }
  }
  d.ms = bench::msSince(start);
  return d;
}

}  // namespace

int main(int argc, char** argv) {
  size_t poses = 54'000;
  int vehicles = 4, viewer_count = 5;
  CLI::App app{"stereomap-bench-trajectory: viewers of a long flight's trajectory"};
  app.add_option("--poses", poses, "poses per vehicle (54,000: three hours at 5 Hz)")
      ->check(CLI::Range(1, 10'000'000));
  app.add_option("--vehicles", vehicles, "vehicles in the session")->check(CLI::Range(1, 64));
  app.add_option("--viewers", viewer_count, "viewers subscribing")->check(CLI::Range(1, 64));
  if (const auto exit = common::parseCommandLine(app, argc, argv)) return *exit;

  core::MapServer server({.resolution = 0.1});
  for (size_t i = 0; i < poses; ++i) {
    for (int v = 0; v < vehicles; ++v) {
      proto::PoseMsg pose;
      pose.vehicle_id = "v" + std::to_string(v + 1);
      pose.session_id = "flight";
      pose.seq = i;
      pose.stamp_ns = 1'000'000'000 + static_cast<int64_t>(i) * 200'000'000;
      // Full-precision numbers, as a vehicle's are (short ones would make shorter JSON).
      const double t = 0.0123456789 * static_cast<double>(i) + 0.1 * v;
      pose.position = {std::cos(t) * 20.0, std::sin(t) * 20.0, 2.0 + 0.1 * std::sin(3 * t)};
      pose.orientation = {0, 0, std::sin(t / 2), std::cos(t / 2)};
      if (!server.ingest(pose)) {
        std::fprintf(stderr, "pose %zu of v%d was rejected\n", i, v + 1);
        return 1;
      }
    }
  }
  viewers::ViewerHub hub(server, nullptr, {});
  std::vector<viewers::ViewerHub::Id> ids;
  for (int w = 0; w < viewer_count; ++w) {
    ids.push_back(hub.connect(true, common::nowNs()));
    hub.receive(ids.back(), R"({"type": "hello", "protocol": 2})", common::nowNs());
  }
  drain(hub, ids);  // the hellos and session lists

  const double live_before = liveMegabytes();
  auto start = bench::Clock::now();
  for (const auto id : ids) {
    hub.receive(id, R"({"type": "subscribe", "session": "flight"})", common::nowNs());
  }
  const double subscribe_ms = bench::msSince(start);
  const double live_after_subscribe = liveMegabytes() - live_before;
  const auto subscribed = drain(hub, ids);

  proto::PoseCorrectionMsg correction;
  correction.vehicle_id = "v1";
  correction.session_id = "flight";
  correction.seq = 1;
  correction.stamp_ns = 1'000'000'000 + static_cast<int64_t>(poses) * 200'000'000;
  correction.keyframes.push_back({1'000'000'000, {0, 0.5, 2.0}, {0, 0, 0, 1}});
  if (!server.ingest(correction)) {
    std::fprintf(stderr, "the correction was rejected\n");
    return 1;
  }
  server.find("flight")->waitUntilIdle();
  start = bench::Clock::now();
  hub.poll(common::nowNs());
  const double poll_ms = bench::msSince(start);
  const double live_after_poll = liveMegabytes() - live_before;
  const auto corrected = drain(hub, ids);

  std::printf(
      "trajectory: %d viewers of %zu poses (%d vehicles): subscribe %.0f ms, live heap +%.1f MB "
      "after it, drain %.0f ms (longest message %.1f ms; %.1f MB in %zu messages, live heap peak "
      "+%.1f MB)\n",
      viewer_count, poses * vehicles, vehicles, subscribe_ms, live_after_subscribe, subscribed.ms,
      subscribed.longest_ms, subscribed.megabytes, subscribed.messages,
      subscribed.peak_live_mb - live_before);
  std::printf(
      "trajectory: a correction: poll %.0f ms, live heap +%.1f MB after it, %zu of %d viewers "
      "closed, drain %.0f ms (longest message %.1f ms; %.1f MB in %zu messages, live heap peak "
      "+%.1f MB)\n",
      poll_ms, live_after_poll, corrected.closed, viewer_count, corrected.ms, corrected.longest_ms,
      corrected.megabytes, corrected.messages, corrected.peak_live_mb - live_before);
  std::printf("trajectory: process RSS %.0f MB\n", bench::residentMegabytes());
  return 0;
}
