// stereomap-bench-link: what a vehicle's stream costs on a radio link and what the map keeps
// of it (issue 22). Flies the scripted flight through sim rooms 1-3 (the typical camera by
// default), makes the clouds as the vehicle does, and fuses at 0.1 m on the true poses twice:
// every cloud as made (the full stream), and what the vehicle's link sends (onboard/link:
// thinned to the map's voxels, frames that bring nothing new skipped, a byte budget), each
// through the codec and back. Scores both maps against the rooms' geometry
// (fusion_accuracy_test's definitions) and ends with the line
//   link: <A> kbit/s per vehicle at 10 Hz, map precision <P> recall <R> (full stream <P0> /
//   <R0>), encode <E> ms/frame
// A counts what the vehicle sends per second as proto::wireBytes counts it: the clouds and
// the poses at 10 Hz, each with its message's fixed part and headers.
#include <CLI/CLI.hpp>
#include <opencv2/core/utility.hpp>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <string>
#include <vector>

#include "common/cli.hpp"
#include "common/statistics.hpp"
#include "onboard/link/cloud_link.hpp"
#include "proto/cloud_codec.hpp"
#include "proto/wire_size.hpp"
#include "tests/support/sim_map_accuracy.hpp"

namespace {

using namespace stereomap;

// The messages as the vehicle sends them, for their size on the wire.
proto::CloudFrameMsg cloudMessage(const common::PointCloud& cloud, proto::CloudEncoding encoding,
                                  std::vector<uint8_t> payload) {
  proto::CloudFrameMsg message;
  message.point_count = static_cast<uint32_t>(cloud.size());
  message.encoding = encoding;
  message.has_intensity = cloud.hasIntensity();
  message.vehicle_id = "sim-1";
  message.session_id = "sim-20261127-120000";
  message.payload = std::move(payload);
  return message;
}
size_t poseBytes() {
  proto::PoseMsg pose;
  pose.vehicle_id = "sim-1";
  pose.session_id = "sim-20261127-120000";
  return proto::wireBytes(pose);
}

double median(std::vector<double> values) {
  return common::median(std::move(values)).value_or(0.0);
}

struct Run {
  testing::SimMapAccuracy accuracy;
  double bytes = 0;          // clouds and poses
  double payload_bytes = 0;  // the clouds' payloads
  double points = 0;         // sent
  double seconds = 0;
  std::vector<double> encode_ms;  // per cloud sent: thinning, decisions and encoding
  link::CloudLinkStats stats;
};

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"stereomap-bench-link: a vehicle's stream on a thin link and the map it makes"};
  std::string camera = "typical";
  std::vector<uint32_t> rooms = {1, 2, 3};
  int frames = 100;
  double resolution = 0.1;
  link::CloudLinkOptions link_options;
  double budget_kbit = 0;
  bool thin = true;
  app.add_option("--camera", camera, "Camera preset")
      ->check(CLI::IsMember({"clean", "typical", "poor"}))
      ->capture_default_str();
  app.add_option("--rooms", rooms, "Sim rooms (seeds)")
      ->delimiter(',')
      ->check(CLI::Range(1u, 1000000u))
      ->capture_default_str();
  app.add_option("--frames", frames, "Frames of each flight (10 Hz)")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  app.add_option("--resolution", resolution, "Map resolution, metres")
      ->check(CLI::Range(0.02, 1.0))
      ->capture_default_str();
  app.add_flag("!--no-thin", thin, "Send whole clouds (no thinning to the map's voxels)");
  app.add_option("--min-new", link_options.min_new_share,
                 "Send a cloud when this share of its voxels is new (0: every cloud)")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  app.add_option("--refresh", link_options.refresh_s, "A voxel counts as new after this, s")
      ->check(CLI::Range(0.01, 1000.0))
      ->capture_default_str();
  app.add_option("--max-interval", link_options.max_interval_s,
                 "Send a cloud at least this often, s")
      ->check(CLI::Range(0.01, 1000.0))
      ->capture_default_str();
  app.add_option("--budget", budget_kbit, "Cloud budget, kbit/s (0: none)")
      ->check(CLI::Range(0.0, 1e6))
      ->capture_default_str();
  app.add_flag("!--no-thinner", link_options.thinner_under_budget,
               "Under a tight budget, send rarer whole clouds instead of thinner ones");
  proto::CloudCodecOptions codec;
  app.add_option("--bits", codec.quantization_bits, "Codec: quantisation bits")
      ->check(CLI::Range(8, 20))
      ->capture_default_str();
  std::string encoding = "auto";
  app.add_option("--codec", encoding,
                 "Cloud encoding (auto: as stereomap-onboard chooses, link::bestEncoding)")
      ->check(CLI::IsMember({"auto", "zstd", "draco", "raw"}))
      ->capture_default_str();
  app.add_option("--speed", codec.draco_speed, "Draco speed (0 smallest .. 10 fastest)")
      ->check(CLI::Range(0, 10))
      ->capture_default_str();
  app.add_flag("!--draco-sequential", codec.draco_kd_tree, "Draco's sequential coder");
  app.add_option("--zstd-level", codec.zstd_level, "zstd level")
      ->check(CLI::Range(1, 19))
      ->capture_default_str();
  if (auto exit_code = stereomap::common::parseCommandLine(app, argc, argv)) return *exit_code;
  cv::setNumThreads(1);
  link_options.map_resolution_m = thin ? resolution : 0;
  link_options.budget_bits_per_s = budget_kbit * 1000;

  auto fly = [&](uint32_t room, bool through_link) {
    Run run;
    testing::SimMapSetup setup;
    setup.room = room;
    setup.frames = frames;
    setup.camera = *sim::CameraModel::preset(camera);
    setup.map = fusion::OccupancyMap::Options::octomapPreset(resolution);
    link::CloudLinkOptions options = link_options;
    if (!through_link) options.map_resolution_m = 0;
    link::CloudLink cloud_link(options);
    proto::CloudCodecOptions cloud_codec = codec;
    cloud_codec.encoding =
        encoding == "auto" ? link::bestEncoding(options) : *proto::parseEncoding(encoding);
    setup.send = [&](common::PointCloud& cloud, const common::Rigid3& T_map_camera,
                     int64_t stamp_ns) {
      const auto start = std::chrono::steady_clock::now();
      if (through_link) {
        auto prepared = cloud_link.prepare(cloud, T_map_camera, stamp_ns);
        if (!prepared) return false;
        cloud = std::move(*prepared);
      }
      cloud_codec.quantization_bits = cloud_link.quantizationBits(cloud, codec.quantization_bits);
      auto payload = proto::encodeCloud(cloud, cloud_codec);
      if (!payload) {
        std::fprintf(stderr, "encoding failed: %s\n", payload.error().message.c_str());
        std::exit(1);
      }
      run.encode_ms.push_back(
          std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
              .count());
      run.payload_bytes += static_cast<double>(payload->size());
      run.points += static_cast<double>(cloud.size());
      const auto message = cloudMessage(cloud, cloud_codec.encoding, std::move(*payload));
      const size_t bytes = proto::wireBytes(message);
      run.bytes += static_cast<double>(bytes);
      if (through_link) cloud_link.sent(stamp_ns, bytes, message.payload.size());
      auto decoded = proto::decodeCloud(message.payload, proto::payloadInfo(message));
      if (!decoded) {
        std::fprintf(stderr, "decoding failed: %s\n", decoded.error().message.c_str());
        std::exit(1);
      }
      cloud = std::move(*decoded);
      return true;
    };
    run.accuracy = testing::measureSimMap(setup);
    run.seconds = frames / 10.0;
    run.bytes += static_cast<double>(frames * poseBytes());
    run.stats = cloud_link.stats();
    return run;
  };

  std::printf(
      "| room | stream | kbit/s | clouds sent | points per cloud | bytes per point | precision | "
      "recall | free | encode ms |\n|---|---|---|---|---|---|---|---|---|---|\n");
  double kbit = 0, precision = 0, recall = 0, precision0 = 0, recall0 = 0;
  std::vector<double> encode_ms;
  for (const uint32_t room : rooms) {
    for (const bool through_link : {false, true}) {
      const Run run = fly(room, through_link);
      const double rate = run.bytes * 8 / run.seconds / 1000;
      const auto sent = static_cast<double>(run.encode_ms.size());
      std::printf("| %u | %s | %.0f | %.0f of %d | %.0f | %.2f | %.4f | %.4f | %.4f | %.2f |\n",
                  room, through_link ? "link" : "full", rate, sent, frames,
                  sent > 0 ? run.points / sent : 0.0,
                  run.points > 0 ? run.payload_bytes / run.points : 0.0, run.accuracy.precision,
                  run.accuracy.recall, run.accuracy.free_space, median(run.encode_ms));
      std::fflush(stdout);
      const double share = 1.0 / static_cast<double>(rooms.size());
      if (through_link) {
        kbit += rate * share;
        precision += run.accuracy.precision * share;
        recall += run.accuracy.recall * share;
        encode_ms.insert(encode_ms.end(), run.encode_ms.begin(), run.encode_ms.end());
      } else {
        precision0 += run.accuracy.precision * share;
        recall0 += run.accuracy.recall * share;
      }
    }
  }
  std::printf(
      "\nlink: %.0f kbit/s per vehicle at 10 Hz, map precision %.3f recall %.3f (full stream "
      "%.3f / %.3f), encode %.2f ms/frame\n",
      kbit, precision, recall, precision0, recall0, median(encode_ms));
  return 0;
}
