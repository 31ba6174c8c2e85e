// stereomap-bench-tiles: what viewers get from the server (issue 14), in process over real
// WebSockets on loopback (the server's Beast layer, protocol 2, and Beast clients):
//   A: a new viewer of fr_campus.bt (1.2 M voxels at 0.2 m): from connecting to holding the
//      coarse pass of its first view (the whole map); B: to holding its budgeted view
//      (view_done); both cold (a fresh session each run: nothing encoded yet); then the
//      time to a view from 20 m above the map's centre (the budget spent near the camera);
//   C: bytes of every level-0 tile together per occupied voxel (the old JSON feed: 11.6);
//   D: 20 viewers subscribed to a live session fed sim frames at 10 Hz through the real ingest
//      path: p95 from a change's publication (the "map" marker's changed_ms) to the marker
//      reaching a viewer, after that change's tiles;
//   E, F: the same with one more viewer that never reads (its socket's receive buffer 4 kB)
//      but asks for every campus tile anew every 100 ms: the rise of the others' p95 and of
//      the process's resident memory beyond the run without it. The server closes it after
//      10 s without progress.
//   stereomap-bench-tiles [--runs R] [--seconds S] [--campus FILE]
#include <utility>  // before Boost.Asio: g++ 12 in C++20 needs std::exchange declared first

#include <spdlog/spdlog.h>
#include <CLI/CLI.hpp>
#include <boost/asio.hpp>
#include <boost/beast.hpp>
#include <nlohmann/json.hpp>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <mutex>
#include <thread>

#include "common/cli.hpp"
#include "common/time.hpp"
#include "server/net/http_server.hpp"
#include "tests/bench/bench_support.hpp"

namespace {

using namespace stereomap;
using namespace stereomap::bench;
namespace asio = boost::asio;
namespace beast = boost::beast;
namespace websocket = beast::websocket;
using tcp = asio::ip::tcp;
using nlohmann::json;

constexpr int kLiveViewers = 20;

// A protocol 2 viewer on a blocking Beast WebSocket.
class Viewer {
 public:
  // `receive_buffer`: the socket's SO_RCVBUF (0: the system's).
  explicit Viewer(uint16_t port, int receive_buffer = 0) {
    auto& socket = ws_.next_layer();
    socket.open(tcp::v4());
    if (receive_buffer > 0)
      socket.set_option(asio::socket_base::receive_buffer_size(receive_buffer));
    socket.connect({asio::ip::make_address("127.0.0.1"), port});
    ws_.handshake("127.0.0.1", "/ws");
    ws_.read_message_max(64u << 20);
    send({{"type", "hello"}, {"protocol", 2}});
  }
  void send(const json& message) {
    ws_.text(true);
    ws_.write(asio::buffer(message.dump()));
  }
  struct Message {
    bool binary = false;
    size_t bytes = 0;
    json text;
  };
  Message read() {
    beast::flat_buffer buffer;
    ws_.read(buffer);
    Message message{!ws_.got_text(), buffer.size(), {}};
    if (!message.binary) message.text = json::parse(beast::buffers_to_string(buffer.data()));
    return message;
  }
  // Reads until a text message of `type`; binary ones are counted.
  json readUntil(const std::string& type, size_t* binary = nullptr) {
    for (;;) {
      auto message = read();
      if (message.binary && binary) ++*binary;
      if (!message.binary && message.text["type"] == type) return message.text;
      if (!message.binary && message.text["type"] == "error") {
        throw std::runtime_error("server error: " + message.text.dump());
      }
    }
  }

 private:
  asio::io_context io_;
  websocket::stream<tcp::socket> ws_{io_};
};

// The camera the viewer's "fit" chooses: from the south-west, above, seeing all of `bounds`.
json fitView(const json& bounds, uint64_t budget) {
  const common::Vec3 low(bounds["min"][0], bounds["min"][1], bounds["min"][2]);
  const common::Vec3 high(bounds["max"][0], bounds["max"][1], bounds["max"][2]);
  const common::Vec3 centre = 0.5 * (low + high);
  const double radius = 0.5 * (high - low).norm();
  const common::Vec3 eye =
      centre + common::Vec3(-0.55, -1, 0.75).normalized() * (radius / std::tan(25 * M_PI / 180));
  return {{"type", "view"}, {"id", 1},       {"eye", {eye.x(), eye.y(), eye.z()}},
          {"fov", 50},      {"height", 800}, {"budget", budget},
          {"error", 2}};
}

double percentile(std::vector<double> values, double p) {
  if (values.empty()) return NAN;
  const size_t at = std::min(values.size() - 1, static_cast<size_t>(p * values.size()));
  std::nth_element(values.begin(), values.begin() + static_cast<long>(at), values.end());
  return values[at];
}

std::string range(const std::vector<double>& v, const char* format = "%.0f") {
  char low[32], high[32];
  std::snprintf(low, sizeof(low), format, *std::min_element(v.begin(), v.end()));
  std::snprintf(high, sizeof(high), format, *std::max_element(v.begin(), v.end()));
  return std::string(low) + "-" + high;
}

struct LiveRun {
  double p95_ms = 0;
  size_t samples = 0;
  double rss_rise_mb = 0;
  bool stuck_closed = false;
};

// `kLiveViewers` viewers of session "live" for `seconds` while frames arrive at 10 Hz (the
// feeder runs throughout); with `stuck`, one more viewer that never reads.
LiveRun liveRun(net::HttpServer& http, const std::string& campus, double seconds, bool stuck) {
  std::atomic<bool> measuring{false}, stop{false};
  std::mutex mutex;
  std::vector<double> latencies;
  std::vector<std::thread> threads;
  std::atomic<int> ready{0};
  for (int i = 0; i < kLiveViewers; ++i) {
    threads.emplace_back([&, i] {
      Viewer viewer(http.port());
      viewer.send({{"type", "subscribe"}, {"session", "live"}});
      viewer.readUntil("subscribed");
      viewer.send({{"type", "view"}, {"id", i}, {"eye", {0, 0, 25}}, {"budget", 1'000'000}});
      viewer.readUntil("view_done");
      ++ready;
      std::vector<double> mine;
      while (!stop) {
        const auto message = viewer.read();
        if (message.binary || message.text["type"] != "map" || !measuring) continue;
        mine.push_back(static_cast<double>(common::nowNs()) * 1e-6 -
                       message.text["changed_ms"].get<double>());
      }
      std::lock_guard lock(mutex);
      latencies.insert(latencies.end(), mine.begin(), mine.end());
    });
  }
  while (ready < kLiveViewers) std::this_thread::sleep_for(std::chrono::milliseconds(20));
  std::unique_ptr<Viewer> stuck_viewer;
  if (stuck) {
    stuck_viewer = std::make_unique<Viewer>(http.port(), 4096);
    // It reads nothing but keeps asking for the campus, finest then coarsest every 100 ms
    // (each view resends every tile): soon far more than the socket buffers hold.
    stuck_viewer->send({{"type", "subscribe"}, {"session", campus}});
    threads.emplace_back([&] {
      json view = fitView({{"min", {-200, -200, -10}}, {"max", {200, 200, 30}}}, 20'000'000);
      try {
        for (int i = 0; !stop; ++i) {
          view["budget"] = i % 2 == 0 ? 20'000'000 : 1'000;  // every tile at level 0, then 6
          stuck_viewer->send(view);
          std::this_thread::sleep_for(std::chrono::milliseconds(100));
        }
      } catch (const std::exception&) {  // the server closed it: what should happen
      }
    });
  }
  LiveRun run;
  const double rss_start = residentMegabytes();
  double rss_max = rss_start;
  measuring = true;
  const auto start = Clock::now();
  while (msSince(start) < seconds * 1000) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    rss_max = std::max(rss_max, residentMegabytes());
    if (stuck && http.viewers() == static_cast<size_t>(kLiveViewers)) run.stuck_closed = true;
  }
  measuring = false;
  stop = true;
  for (auto& thread : threads) thread.join();  // each returns at its next message
  run.p95_ms = percentile(latencies, 0.95);
  run.samples = latencies.size();
  run.rss_rise_mb = rss_max - rss_start;
  return run;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"stereomap-bench-tiles: viewers of fr_campus and of a live session over WebSockets"};
  int runs = 3;
  double seconds = 15;
  std::string campus_file = std::string(STEREOMAP_DATA_DIR) + "/octomap_samples/fr_campus.bt";
  app.add_option("--runs", runs, "repetitions of A/B and of the live pair")
      ->check(CLI::Range(1, 20));
  app.add_option("--seconds", seconds,
                 "length of each live run (the stuck viewer is closed "
                 "after 10 s)")
      ->check(CLI::Range(2.0, 600.0));
  app.add_option("--campus", campus_file, "the large map")->check(CLI::ExistingFile);
  if (auto exit_code = stereomap::common::parseCommandLine(app, argc, argv)) return *exit_code;
  spdlog::set_level(spdlog::level::err);

  std::printf("rendering 300 sim frames...\n");
  std::fflush(stdout);
  const auto frames = simFrames(300);
  size_t octomap_bytes = 0;
  const std::string campus_ot = campusSnapshot(campus_file, octomap_bytes);

  core::MapServer server({.resolution = 0.2, .queue_capacity = 200});
  auto http = net::HttpServer::create({.address = "127.0.0.1", .port = 0}, server).value();
  http->start();

  // A, B, C: a cold campus session per run.
  std::vector<double> first_view_ms, budget_view_ms, zoom_ms;
  double bytes_per_voxel = 0;
  std::string campus;
  for (int run = 0; run < runs; ++run) {
    if (!campus.empty()) server.unload(campus);
    campus = "campus-" + std::to_string(run);
    const auto session = campusSession(server, campus, campus_ot);
    const auto start = Clock::now();
    Viewer viewer(http->port());
    viewer.send({{"type", "subscribe"}, {"session", campus}});
    const json subscribed = viewer.readUntil("subscribed");
    viewer.send(fitView(subscribed["bounds"], 1'000'000));
    size_t tiles = 0;
    const json plan = viewer.readUntil("plan", &tiles);
    const size_t coarse = plan["coarse_tiles"];
    while (tiles < coarse) tiles += viewer.read().binary;
    first_view_ms.push_back(msSince(start));
    viewer.readUntil("view_done", &tiles);
    budget_view_ms.push_back(msSince(start));
    // Then the operator zooms in: 20 m above the map's centre, where the budget is spent.
    const json& b = subscribed["bounds"];
    const double cx = 0.5 * (b["min"][0].get<double>() + b["max"][0].get<double>());
    const double cy = 0.5 * (b["min"][1].get<double>() + b["max"][1].get<double>());
    json zoom = fitView(subscribed["bounds"], 1'000'000);
    zoom["id"] = 2;
    zoom["eye"] = {cx, cy, b["min"][2].get<double>() + 20};
    const auto zoom_start = Clock::now();
    viewer.send(zoom);
    size_t zoom_tiles = 0;
    const json zoom_plan = viewer.readUntil("plan");
    viewer.readUntil("view_done", &zoom_tiles);
    zoom_ms.push_back(msSince(zoom_start));
    std::printf(
        "run %d: %zu tiles, coarse level %d (%zu tiles) in %.0f ms, %llu cells in %.0f ms; "
        "zoomed in: %zu tiles, %llu cells in %.0f ms\n",
        run + 1, tiles, plan["coarse_level"].get<int>(), coarse, first_view_ms.back(),
        static_cast<unsigned long long>(plan["cells"].get<uint64_t>()), budget_view_ms.back(),
        zoom_tiles, static_cast<unsigned long long>(zoom_plan["cells"].get<uint64_t>()),
        zoom_ms.back());
    std::fflush(stdout);
    if (run == 0) {
      size_t bytes = 0;
      for (const auto& tile : session->tiles().all()) bytes += tile->encoded(0)->size();
      bytes_per_voxel = static_cast<double>(bytes) /
                        static_cast<double>(session->tiles().summary().occupied_voxels);
    }
  }

  // D, E, F: the live session, fed at 10 Hz from here on.
  std::atomic<bool> feeding{true};
  std::thread feeder([&] {
    auto next = Clock::now();
    for (uint64_t i = 0; feeding; ++i) {
      auto frame = frames[i % frames.size()];
      frame.session_id = "live";
      frame.seq = i;
      frame.stamp_ns = 1'000'000 + static_cast<int64_t>(i) * 100'000'000;
      server.ingest(frame);
      next += std::chrono::milliseconds(100);
      std::this_thread::sleep_until(next);
    }
  });
  std::this_thread::sleep_for(std::chrono::seconds(2));  // the session exists, fusion warm
  std::vector<double> base_p95, stuck_p95, rises, extra_mb;
  for (int run = 0; run < runs; ++run) {
    const LiveRun base = liveRun(*http, campus, seconds, false);
    const LiveRun with_stuck = liveRun(*http, campus, seconds, true);
    base_p95.push_back(base.p95_ms);
    stuck_p95.push_back(with_stuck.p95_ms);
    rises.push_back(100.0 * (with_stuck.p95_ms / base.p95_ms - 1));
    extra_mb.push_back(std::max(0.0, with_stuck.rss_rise_mb - base.rss_rise_mb));
    std::printf(
        "live run %d: p95 %.1f ms (%zu markers) alone, %.1f ms (%zu) with a stuck viewer "
        "(%s by the server); RSS rise %.1f MB vs %.1f MB\n",
        run + 1, base.p95_ms, base.samples, with_stuck.p95_ms, with_stuck.samples,
        with_stuck.stuck_closed ? "closed" : "not closed", with_stuck.rss_rise_mb,
        base.rss_rise_mb);
    std::fflush(stdout);
  }
  feeding = false;
  feeder.join();
  http->stop();

  std::printf(
      "ranges over %d runs: first view %s ms, budget view %s ms, zoomed in %s ms; live p95 "
      "%s ms, with a stuck viewer %s ms (%s %%), +%s MB\n",
      runs, range(first_view_ms).c_str(), range(budget_view_ms).c_str(), range(zoom_ms).c_str(),
      range(base_p95, "%.1f").c_str(), range(stuck_p95, "%.1f").c_str(), range(rises).c_str(),
      range(extra_mb, "%.1f").c_str());
  // The last line, exactly as issue 14 names it: the worst run of each.
  std::printf(
      "tiles: fr_campus first view %.0f ms, budget view %.0f ms, %.3f B/voxel; live p95 "
      "%.0f ms at %d viewers; stuck viewer +%.0f%% p95, +%.0f MB\n",
      *std::max_element(first_view_ms.begin(), first_view_ms.end()),
      *std::max_element(budget_view_ms.begin(), budget_view_ms.end()), bytes_per_voxel,
      *std::max_element(base_p95.begin(), base_p95.end()), kLiveViewers,
      std::max(0.0, *std::max_element(rises.begin(), rises.end())),
      *std::max_element(extra_mb.begin(), extra_mb.end()));
  return 0;
}
