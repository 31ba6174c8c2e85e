// Cross-process, through a real shaped link (issue 22): stereomap-server and a simulated
// vehicle in two network namespaces joined by a veth pair, with Cyclone configured as for a
// radio link (config/cyclonedds-radio.xml). The vehicle flies 30 s at 10 Hz with
// --link-budget 1Mbit, once on the bare veth and once with the link shaped to 1 Mbit/s (tc
// tbf, a 400 ms queue), 1 % random loss each way (nftables) and 50 ms more on the way to the
// server (a UDP relay: this kernel has no netem). Checked on the shaped run:
// poses arrive at 10 Hz, 95 % of them within 200 ms of their stamp (the server's
// stereomap_vehicle_pose_latency_seconds), the map grows while the vehicle flies, its
// precision stays within 0.01 of the bare run's, the queues drain and neither process grows
// beyond a bound. Skips where namespaces cannot be made (not root).
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <fstream>
#include <regex>
#include <sstream>
#include <thread>

#include "onboard/sim/sim_source.hpp"
#include "tests/support/linked_namespaces.hpp"
#include "tests/support/map_score.hpp"
#include "tests/support/server_fixture.hpp"

namespace stereomap::testing {
namespace {

using namespace std::chrono_literals;

constexpr int kFrames = 300;  // 30 s at 10 Hz
constexpr double kResolution = 0.1;
constexpr double kMaxRange = 6.0;
constexpr const char* kSession = "shaped";

std::string radioConfig() {
  return std::string(STEREOMAP_SOURCE_DIR) + "/config/cyclonedds-radio.xml";
}

// Resident memory of a process, kB (from any namespace).
long rssKb(pid_t pid) {
  std::ifstream status("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  while (std::getline(status, line)) {
    if (line.rfind("VmRSS:", 0) == 0) return std::atol(line.c_str() + 6);
  }
  return 0;
}

struct Flight {
  MapScore score;
  double poses = 0;
  double pose_latency_p50_s = 0, pose_latency_p95_s = 0;
  double occupied_early = 0, occupied_late = 0;
  long server_rss_early = 0, server_rss_late = 0, vehicle_rss_early = 0, vehicle_rss_late = 0;
  double vehicle_kbit_s = 0;  // from the vehicle's summary
  int late_frames = -1;       // frames the vehicle finished after their 100 ms
  double frame_median_s = 0;  // the vehicle's own work per frame (its summary's median)
  uint64_t relayed = 0;       // datagrams that took the delay's way
  LinkedNamespaces::QueueStats vehicle_queue, server_queue;
  std::string logs;
};

Flight fly(int domain, int subnet, const std::optional<LinkShape>& shape) {
  Flight flight;
  LinkedNamespaces link(shape ? "shp" : "bare", subnet);
  if (shape) {
    link.shape(*shape);
    link.delayToServer(50ms, domain);
  }
  std::unique_ptr<ServerProcess> server;
  {
    const auto in = link.enter(link.server());
    server = std::make_unique<ServerProcess>(
        domain, std::vector<std::string>{"--resolution", std::to_string(kResolution),
                                         "--dds-config", radioConfig()});
  }
  const std::string onboard_log = server->logPath() + ".onboard";
  std::unique_ptr<ChildProcess> onboard;
  {
    const auto in = link.enter(link.vehicle());
    onboard = std::make_unique<ChildProcess>(
        onboardArgs(domain, kSession, kFrames,
                    {"--rate", "10", "--seed", "1", "--camera", "typical", "--map-resolution",
                     std::to_string(kResolution), "--min-new", "0.1", "--link-budget", "1Mbit",
                     "--dds-config", radioConfig(), "--wait-for-server", "20"}),
        onboard_log);
  }
  const auto in = link.enter(link.server());
  auto status = [&] {
    const auto reply = server->get(std::string("/api/sessions/") + kSession);
    return reply.status == 200 ? nlohmann::json::parse(reply.body) : nlohmann::json{};
  };
  // Early: 10 s into the flight (the vehicle streams once it has found the server).
  EXPECT_TRUE(waitUntil(30s, [&] { return !status().empty(); })) << server->log();
  std::this_thread::sleep_for(10s);
  flight.occupied_early = status().value("occupied_voxels", 0.0);
  flight.server_rss_early = rssKb(server->process().pid());
  flight.vehicle_rss_early = rssKb(onboard->pid());
  std::this_thread::sleep_for(15s);
  flight.server_rss_late = rssKb(server->process().pid());
  flight.vehicle_rss_late = rssKb(onboard->pid());

  const auto code = onboard->waitExit(60s);
  EXPECT_TRUE(code.has_value()) << "the vehicle did not finish: a stall";
  EXPECT_EQ(code.value_or(-1), 0);
  EXPECT_TRUE(waitUntil(30s, [&] { return status().value("fusion_backlog", -1) == 0; }));
  const auto metrics = server->get("/metrics").body;
  const std::string labels = std::string("{session=\"") + kSession + "\",vehicle=\"sim-1\"";
  flight.pose_latency_p50_s = seriesValue(
      metrics, "stereomap_vehicle_pose_latency_seconds" + labels + ",quantile=\"0.5\"}");
  flight.pose_latency_p95_s = seriesValue(
      metrics, "stereomap_vehicle_pose_latency_seconds" + labels + ",quantile=\"0.95\"}");
  const auto final_status = status();
  flight.poses = final_status.value("poses", 0.0);
  flight.occupied_late = final_status.value("occupied_voxels", 0.0);
  std::this_thread::sleep_for(1s);
  flight.relayed = link.relayed();
  flight.vehicle_queue = link.queue(link.vehicle());
  flight.server_queue = link.queue(link.server());

  const auto map_reply = server->get(std::string("/api/sessions/") + kSession + "/map.bt");
  EXPECT_EQ(map_reply.status, 200);
  const sim::SimSource truth({.seed = 1, .rate_hz = 10.0, .max_frames = kFrames});
  if (map_reply.status == 200) {
    flight.score = scoreMap(map_reply.body, kResolution, truth, kFrames, kMaxRange);
  }
  std::ifstream summary(onboard_log);
  std::stringstream text;
  text << summary.rdbuf();
  flight.logs = text.str();
  std::smatch match;
  if (std::regex_search(flight.logs, match, std::regex(R"(done: .*)"))) {
    std::printf("vehicle's summary:%s\n", match[0].str().c_str());
  }
  if (std::regex_search(flight.logs, match, std::regex(R"((\d+) late,)"))) {
    flight.late_frames = std::stoi(match[1]);
  }
  if (std::regex_search(flight.logs, match, std::regex(R"(frame ([0-9.]+) ms)"))) {
    flight.frame_median_s = std::stod(match[1]) / 1000;
  }
  if (std::regex_search(flight.logs, match, std::regex(R"(link: sent (\d+) kbit/s)"))) {
    flight.vehicle_kbit_s = std::stod(match[1]);
  }
  std::printf(
      "%s link: %.0f poses, pose age p50 %.0f ms p95 %.0f ms, vehicle %.0f kbit/s, occupied "
      "voxels %.0f at 10 s and %.0f at the end, precision %.4f coverage %.4f, packets lost "
      "%ld / %ld, tbf drops %ld / %ld, %llu datagrams delayed, RSS server %ld -> %ld kB, vehicle "
      "%ld -> %ld kB\n",
      shape ? "shaped" : "bare", flight.poses, flight.pose_latency_p50_s * 1000,
      flight.pose_latency_p95_s * 1000, flight.vehicle_kbit_s, flight.occupied_early,
      flight.occupied_late, flight.score.precision, flight.score.coverage,
      flight.vehicle_queue.lost, flight.server_queue.lost, flight.vehicle_queue.dropped,
      flight.server_queue.dropped, static_cast<unsigned long long>(flight.relayed),
      flight.server_rss_early, flight.server_rss_late, flight.vehicle_rss_early,
      flight.vehicle_rss_late);
  return flight;
}

TEST(ShapedLink, AVehicleOnAOneMegabitLossyLinkKeepsItsPosesLiveAndItsMapRight) {
  if (auto why = LinkedNamespaces::unavailable()) GTEST_SKIP() << *why;
  const Flight bare = fly(94, 94, std::nullopt);
  const Flight shaped = fly(95, 95, LinkShape{.rate = "1mbit", .loss_percent = 1});

  for (const Flight* flight : {&bare, &shaped}) {
    // Pose ages mean nothing once the vehicle falls behind real time (they grow by the
    // backlog): the machine was too busy for this test (it runs alone under ctest).
    EXPECT_GE(flight->late_frames, 0);
    EXPECT_LE(flight->late_frames, kFrames / 20) << "the vehicle fell behind real time";
    // Poses at 10 Hz: every one of the 300 arrives (reliable, resent after a loss).
    EXPECT_GE(flight->poses, kFrames * 0.99) << flight->logs;
    EXPECT_GT(flight->occupied_early, 0);
    EXPECT_GT(flight->occupied_late, flight->occupied_early * 1.2);  // the map grows
    EXPECT_LE(flight->vehicle_kbit_s, 1000);
    EXPECT_GT(flight->vehicle_kbit_s, 0);
    // The queues drain once the vehicle stops.
    EXPECT_EQ(flight->vehicle_queue.backlog_bytes, 0);
    // Nothing grows without bound between 10 s and 25 s: the vehicle's memory stays level
    // (measured within 3 %), the server's grows with its map (measured 6-7 %).
    EXPECT_LE(flight->vehicle_rss_late, flight->vehicle_rss_early * 1.1);
    EXPECT_LE(flight->server_rss_late, flight->server_rss_early * 1.2);
  }
  EXPECT_LE(shaped.pose_latency_p95_s, 0.2);
  // The delay is there: every datagram to the server took it. A pose's age is the vehicle's
  // work on its frame plus the way, and the work varies between the two flights by more than
  // the margin (a CI run: 77.5 against 75.2 ms a frame, and ages 71 against 116 ms), so each
  // flight's ages are compared net of its own median frame time.
  EXPECT_GT(bare.frame_median_s, 0);
  EXPECT_GT(shaped.frame_median_s, 0);
  EXPECT_GE(shaped.pose_latency_p50_s - shaped.frame_median_s,
            bare.pose_latency_p50_s - bare.frame_median_s + 0.045);
  EXPECT_GT(shaped.relayed, static_cast<uint64_t>(kFrames));
  EXPECT_GE(shaped.score.precision, bare.score.precision - 0.01);
  ::testing::Test::RecordProperty("shaped_pose_p95_ms",
                                  std::to_string(shaped.pose_latency_p95_s * 1000));
  ::testing::Test::RecordProperty("shaped_precision", std::to_string(shaped.score.precision));
}

}  // namespace
}  // namespace stereomap::testing
