// stereomap-onboard: the vehicle side. Reads stereo frames from a source, estimates its pose
// by stereo visual odometry, computes depth, and streams compressed clouds and poses to
// stereomap-server over DDS. With --no-publish it runs the odometry alone (trajectory files,
// a progress bar and a summary).
#include <spdlog/spdlog.h>
#include <CLI/CLI.hpp>

#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <ctime>
#include <filesystem>

#include "common/shutdown.hpp"
#include "common/trajectory.hpp"
#include "onboard/camera/dataset_source.hpp"
#include "onboard/link/cloud_link.hpp"
#include "onboard/pipeline/pipeline.hpp"
#include "onboard/sim/deck.hpp"
#include "onboard/sim/sim_source.hpp"
#include "proto/dds_cli.hpp"
#include "proto/wire_size.hpp"

namespace {

std::string defaultSessionName() {
  const std::time_t now = std::time(nullptr);
  char text[32];
  std::strftime(text, sizeof(text), "sim-%Y%m%d-%H%M%S", std::gmtime(&now));
  return text;
}

}  // namespace

int main(int argc, char** argv) {
  using namespace stereomap;
  common::Shutdown shutdown;  // first: blocks SIGINT/SIGTERM for every later thread

  CLI::App app{"stereomap-onboard: stream a vehicle's stereo depth and pose to the server"};
  std::string source_spec = "sim";
  uint64_t frames = 0;
  double rate_hz = 10.0;
  pipeline::PipelineOptions options;
  options.session_id = defaultSessionName();
  proto::DdsOptions dds;
  uint32_t seed = 1;
  std::string stereo_preset = "fast";
  double noise_sigma = 0, blur_sigma = 0;
  std::string camera_preset;
  std::string vo = "fast", trajectory_out, kitti_out, odometry_out, truth_out;
  bool no_publish = false;
  double wait_s = 3.0;
  double paper_resolution = 0;
  std::string calibration_file;
  std::string landing_mode = "off";
  app.add_option("--source", source_spec,
                 "Frame source: sim, sim:deck (a descent onto a moving ship's deck with the "
                 "landing pad), kitti:DIR, euroc:DIR, folder:DIR or camera:LEFT,RIGHT")
      ->capture_default_str();
  app.add_option("--calib", calibration_file,
                 "Stereo calibration (ours, OpenCV stereo_calib, KITTI calib.txt); overrides "
                 "the source's own")
      ->check(CLI::ExistingFile);
  app.add_option("--frames", frames, "Stop after N frames (0: run until Ctrl-C)")
      ->capture_default_str();
  app.add_option("--rate", rate_hz, "Frames per second (0: as fast as possible)")
      ->check(CLI::Range(0.0, 1000.0))
      ->capture_default_str();
  app.add_option("--session", options.session_id, "Session name (letters, digits, . _ -)")
      ->capture_default_str();
  app.add_option("--vehicle", options.vehicle_id, "Vehicle id")->capture_default_str();
  proto::addDdsFlags(app, dds);
  app.add_option("--seed", seed, "Simulated room's seed")->capture_default_str();
  app.add_option("--stereo", stereo_preset,
                 "Stereo configuration: fast (real time) or accurate (docs/BENCHMARKS.md)")
      ->check(CLI::IsMember({"fast", "accurate"}))
      ->capture_default_str();
  std::string noise_handling = "auto";
  app.add_option("--noise-handling", noise_handling,
                 "Image noise in the depth step: auto (estimated from the images; noisy "
                 "images are matched smoothed with larger blocks and their depth averaged over "
                 "frames, docs/BENCHMARKS.md), on (always so) or off (frame by frame, as for "
                 "clean images)")
      ->check(CLI::IsMember({"auto", "on", "off"}))
      ->capture_default_str();
  app.add_option("--max-range", options.stereo.cloud.max_range_m, "Cloud range limit, metres")
      ->check(CLI::Range(0.5, 100.0))
      ->capture_default_str();
  std::string codec = "auto";
  app.add_option("--codec", codec,
                 "Cloud encoding: auto (the smallest, docs/BENCHMARKS.md: draco for clouds "
                 "thinned to the map's voxels, zstd for whole ones), draco (kd-tree), zstd "
                 "(quantised, delta coded, zstd) or raw (floats)")
      ->check(CLI::IsMember({"auto", "draco", "zstd", "raw"}))
      ->capture_default_str();
  app.add_option("--quantization-bits", options.codec.quantization_bits,
                 "Position quantisation bits (draco and zstd); thinned clouds use fewer when "
                 "1/64 of a voxel allows")
      ->check(CLI::Range(6, 20))
      ->capture_default_str();
  app.add_option("--camera", camera_preset,
                 "Sim: the camera model: clean (exact images; the room's default), typical "
                 "(noise sigma 2 at mid grey, 5 % left/right gain mismatch, defocus, motion "
                 "blur, vignetting, gamma) or poor (sigma 4, 10 %, stronger blur); the deck's "
                 "default is typical. --image-noise and --image-blur "
                 "override its read noise and defocus")
      ->check(CLI::IsMember({"clean", "typical", "poor"}));
  app.add_option("--image-noise", noise_sigma, "Sim: Gaussian image noise, grey levels")
      ->check(CLI::Range(0.0, 50.0))
      ->capture_default_str();
  app.add_option("--image-blur", blur_sigma, "Sim: Gaussian blur of the images, pixels")
      ->check(CLI::Range(0.0, 10.0))
      ->capture_default_str();
  app.add_option("--vo", vo,
                 "Pose from: fast (stereo visual odometry), paper (the stereo-VO paper's "
                 "method) or gt (the source's ground truth)")
      ->check(CLI::IsMember({"fast", "paper", "gt"}))
      ->capture_default_str();
  app.add_option("--trajectory-out", trajectory_out,
                 "Write the poses (T_map_body) as TUM: t tx ty tz qx qy qz qw; with "
                 "--pose-graph, every frame through the final graph");
  app.add_flag("--pose-graph", options.pose_graph,
               "Correct the odometry with a pose graph over its keyframes: loop closures and "
               "joins of lost tracks by place recognition, solved on a worker thread; the "
               "corrected keyframe poses are sent to the server, which fuses its map again");
  app.add_option("--odometry-trajectory-out", odometry_out,
                 "Write the odometry's own poses (T_map_body, TUM), before any correction");
  app.add_option("--truth-out", truth_out,
                 "Write the source's ground-truth poses (T_map_body, TUM), where it has them");
  app.add_option("--kitti-poses-out", kitti_out,
                 "Write the left camera's poses relative to the first frame, KITTI format");
  app.add_flag("--no-publish", no_publish,
               "No DDS: run the odometry alone (with a progress bar and a summary)");
  app.add_option("--voxel-downsample", options.stereo.cloud.voxel_m,
                 "Keep one point per voxel of this edge, metres (0: off; the 5x2 blocks stay)")
      ->check(CLI::Range(0.0, 10.0))
      ->capture_default_str();
  app.add_option("--min-disparity-for-resolution", paper_resolution,
                 "Skip disparities below the octree-mapping paper's d_min = ceil(sqrt(b*f*0.5/r)) "
                 "for map resolution r metres (0: off)")
      ->check(CLI::Range(0.0, 10.0));
  app.add_option("--landing", landing_mode,
                 "Watch for the landing pad and publish it (LandingTarget): default (PnP refined "
                 "on both images) or patent (the patent's linear solution); off: no watch")
      ->check(CLI::IsMember({"off", "default", "patent"}))
      ->capture_default_str();
  std::string link_budget = "off";
  app.add_option("--link-budget", link_budget,
                 "Keep the stream under this rate on the radio link (1Mbit, 500kbit, ...; off): "
                 "clouds are sent less often, poses keep their rate")
      ->capture_default_str();
  auto& link = *options.link;
  app.add_option("--map-resolution", link.map_resolution_m,
                 "The server's map resolution: clouds are thinned to one point per voxel of it "
                 "(0: sent whole)")
      ->check(CLI::Range(0.0, 10.0))
      ->capture_default_str();
  app.add_option("--min-new", link.min_new_share,
                 "Send a cloud when this share of its voxels was not sent in the last 2 s, or "
                 "after 1 s without one (0: every cloud)")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  app.set_config("--config", "", "Read these options from a TOML or INI file (name = value)");
  app.allow_config_extras(CLI::config_extras_mode::error);  // a typo in the file is an error
  app.add_option("--wait-for-server", wait_s, "Seconds to wait for a server before streaming")
      ->check(CLI::Range(0.0, 600.0))
      ->capture_default_str();
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& error) {
    return app.exit(error) == 0 ? 0 : 2;
  }

  if (options.session_id.empty() || options.session_id.size() > proto::kMaxIdLength ||
      options.session_id.find_first_not_of("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ"
                                           "0123456789._-") != std::string::npos) {
    spdlog::error("--session '{}' must be 1-64 letters, digits, '.', '_' or '-'",
                  options.session_id);
    return 2;
  }
  if (auto budget = link::parseBitRate(link_budget); !budget) {
    spdlog::error("--link-budget: {}", budget.error().message);
    return 2;
  } else if (*budget > 0) {
    proto::PoseMsg pose;
    pose.vehicle_id = options.vehicle_id;
    pose.session_id = options.session_id;
    const double poses =
        static_cast<double>(proto::wireBytes(pose)) * 8 * (rate_hz > 0 ? rate_hz : 30.0);
    link.budget_bits_per_s = link::cloudShare(*budget, poses);
    if (link.budget_bits_per_s <= 0) {
      spdlog::error("--link-budget {}: the poses alone need {:.0f} kbit/s", link_budget,
                    poses / 1000);
      return 2;
    }
  }
  options.codec.encoding =
      codec == "auto" ? link::bestEncoding(link) : *proto::parseEncoding(codec);  // IsMember
  options.rate_hz = rate_hz;
  options.stereo.matcher = stereo_preset == "accurate" ? stereo::MatcherOptions::accurate()
                                                       : stereo::MatcherOptions::fast();
  options.stereo.noise = noise_handling == "on"    ? stereo::NoiseHandling::kOn
                         : noise_handling == "off" ? stereo::NoiseHandling::kOff
                                                   : stereo::NoiseHandling::kAuto;
  options.wait_for_server = std::chrono::milliseconds(static_cast<int64_t>(wait_s * 1000));

  // --camera replaces the source's camera model; --image-noise and --image-blur then set its
  // read noise and defocus.
  auto applyCameraFlags = [&](sim::CameraModel& model) {
    if (!camera_preset.empty()) model = *sim::CameraModel::preset(camera_preset);
    if (app.count("--image-noise") > 0) model.noise_sigma = noise_sigma;
    if (app.count("--image-blur") > 0) model.blur_sigma = blur_sigma;
  };
  std::unique_ptr<camera::FrameSource> source;
  if (source_spec == "sim:deck") {
    sim::DeckSourceOptions deck{
        .seed = seed, .rate_hz = rate_hz > 0 ? rate_hz : 10.0, .max_frames = frames};
    applyCameraFlags(deck.render.camera);
    source = std::make_unique<sim::DeckSource>(deck);
    // Odometry would follow the deck (the scene moves with it); the sim's navigation stands
    // in for the vehicle's GPS/INS, as the landing patent uses it.
    if (app.count("--vo") == 0) {
      vo = "gt";
      spdlog::info(
          "sim:deck: poses from the sim's navigation (stands in for GPS/INS; --vo to "
          "change)");
    }
  } else if (source_spec == "sim") {
    sim::SimSourceOptions sim_options{
        .seed = seed, .rate_hz = rate_hz > 0 ? rate_hz : 10.0, .max_frames = frames};
    applyCameraFlags(sim_options.render.camera);
    source = std::make_unique<sim::SimSource>(sim_options);
  } else {
    camera::DatasetOptions dataset{.max_frames = frames, .rate_hz = rate_hz > 0 ? rate_hz : 10.0};
    if (!calibration_file.empty()) dataset.calibration_file = calibration_file;
    auto opened = camera::openDatasetSource(source_spec, dataset);
    if (!opened) {
      spdlog::error("{}", opened.error().message);
      return opened.error().code == common::ErrorCode::kInvalidArgument ? 2 : 1;
    }
    source = std::move(opened).value();
  }

  if (paper_resolution > 0) {
    const auto& camera = source->camera();
    options.stereo.matcher.min_disparity =
        stereo::minimumDisparity(camera.baseline, camera.fx, paper_resolution);
    spdlog::info("minimum disparity {} px (depth up to {:.2f} m) for {} m voxels",
                 options.stereo.matcher.min_disparity,
                 camera.depthFromDisparity(options.stereo.matcher.min_disparity), paper_resolution);
  }

  options.pose_source =
      vo == "gt" ? pipeline::PoseSource::kGroundTruth : pipeline::PoseSource::kOdometry;
  options.odometry.mode = vo == "paper" ? odometry::VoMode::kPaper : odometry::VoMode::kFast;
  options.depth = !no_publish;  // the clouds only matter to a server
  if (landing_mode != "off") {
    options.landing = landing::LandingWatchOptions{};
    options.landing->pose.mode =
        landing_mode == "patent" ? landing::PoseMode::kPatent : landing::PoseMode::kDefault;
  }

  // Trajectory files, and a progress bar when running the odometry alone.
  // Kept only when asked for: a live vehicle runs until Ctrl-C.
  common::Trajectory trajectory, kitti_poses, odometry_poses, truth_poses;
  std::optional<common::Rigid3> first_camera;
  uint64_t n = 0;
  const bool bar = no_publish && isatty(STDERR_FILENO);
  options.on_frame = [&](const pipeline::FrameReport& r) {
    const double t = static_cast<double>(r.stamp_ns) * 1e-9;
    ++n;
    if (!trajectory_out.empty()) trajectory.push_back({t, r.T_map_body});
    if (!odometry_out.empty()) odometry_poses.push_back({t, r.T_map_body_odometry});
    if (!truth_out.empty() && r.T_map_body_truth) truth_poses.push_back({t, *r.T_map_body_truth});
    if (!first_camera) first_camera = r.T_map_camera;
    if (!kitti_out.empty()) kitti_poses.push_back({t, first_camera->inverse() * r.T_map_camera});
    if (bar) {
      const int filled = frames > 0 ? static_cast<int>(30 * n / frames) : static_cast<int>(n % 31);
      std::fprintf(stderr, "\r[%-30s] %llu%s frames, odometry %s, %.1f ms",
                   std::string(filled, '#').c_str(), static_cast<unsigned long long>(n),
                   frames > 0 ? ("/" + std::to_string(frames)).c_str() : "",
                   odometry::stateName(r.state), r.odometry_ms);
    }
  };
  if (no_publish) options.progress_every = 0;

  std::shared_ptr<proto::Participant> participant;
  std::unique_ptr<pipeline::VehiclePublisher> publisher;
  if (!no_publish) {
    auto created = proto::Participant::create(dds);
    if (!created) {
      spdlog::error("{}", created.error().message);
      return 1;
    }
    participant = std::move(created).value();
    auto made = pipeline::VehiclePublisher::create(participant);
    if (!made) {
      spdlog::error("{}", made.error().message);
      return 1;
    }
    publisher = std::move(made).value();
    spdlog::info("vehicle '{}' session '{}' on DDS domain {}: {} at {} Hz{}, pose from {}",
                 options.vehicle_id, options.session_id, dds.domain_id, source->describe(), rate_hz,
                 frames > 0 ? fmt::format(", {} frames", frames) : std::string(", until Ctrl-C"),
                 vo);
  } else {
    spdlog::info("odometry ({}) on {}, nothing published", vo, source->describe());
  }
  const auto summary = pipeline::runPipeline(*source, publisher.get(), options, shutdown);
  if (bar) std::fprintf(stderr, "\n");
  if (options.pose_graph && summary.corrected_T_map_body.size() == trajectory.size()) {
    for (size_t i = 0; i < trajectory.size(); ++i) {
      trajectory[i].pose = summary.corrected_T_map_body[i];
    }
  }
  if (options.pose_graph) {
    spdlog::info(
        "pose graph: {} keyframes, {} loop closures, {} of {} later tracks joined, "
        "longest solve {:.1f} ms",
        summary.graph.keyframes, summary.graph.loops, summary.graph.joined_tracks,
        std::max(0, summary.graph.tracks - 1), summary.graph.solve_ms_max);
  }
  for (const auto& [path, text] : {std::pair{trajectory_out, common::tumText(trajectory)},
                                   std::pair{kitti_out, common::kittiText(kitti_poses)},
                                   std::pair{odometry_out, common::tumText(odometry_poses)},
                                   std::pair{truth_out, common::tumText(truth_poses)}}) {
    if (path.empty()) continue;
    if (auto written = common::writeText(path, text); !written) {
      spdlog::error("{}", written.error().message);
      return 1;
    }
    spdlog::info("wrote {} poses to {}", n, path);
  }
  if (options.pose_source == pipeline::PoseSource::kOdometry) {
    spdlog::info("odometry: {} frames, {} lost, {} degraded, {:.1f} ms per frame (median)",
                 summary.frames, summary.lost_frames, summary.degraded_frames,
                 summary.median_odometry_ms);
    // Half a pixel of disparity bias costs several percent of scale at 20 m.
    if (std::abs(summary.right_offset_px) > 0.5) {
      spdlog::warn(
          "the right image sits {:+.2f} px off its calibration (estimated by the odometry, "
          "which corrects for it); the stereo calibration needs redoing",
          summary.right_offset_px);
    } else if (options.odometry.mode == odometry::VoMode::kFast) {
      spdlog::info(
          "stereo calibration check: right image offset {:+.2f} px, right camera gain {:.3f}",
          summary.right_offset_px, summary.right_gain);
    }
  }
  if (options.landing) {
    spdlog::info("landing pad: tracked in {} of {} frames, {} poses published",
                 summary.landing_tracked, summary.frames, summary.landing_poses);
  }
  if (no_publish) return 0;
  spdlog::info(
      "done: {} frames{}, {} points ({:.0f} per frame), depth {:.1f} ms, encode {:.1f} ms, frame "
      "{:.1f} ms (medians), {} late, {} publish errors; images {} (noise sigma {:.1f} grey "
      "levels)",
      summary.frames, summary.stopped ? " (stopped)" : "", summary.points,
      summary.frames ? static_cast<double>(summary.points) / summary.frames : 0.0,
      summary.median_depth_ms, summary.median_encode_ms, summary.median_frame_ms,
      summary.late_frames, summary.publish_errors, summary.noisy_images ? "noisy" : "clean",
      summary.image_noise_sigma);
  const auto& sent = summary.link;
  spdlog::info(
      "link: sent {:.0f} kbit/s (clouds and poses), {} of {} clouds ({} skipped with nothing new, "
      "{} over the budget, {} thinner for it), {:.0f} points and {:.1f} KiB per cloud sent",
      summary.stream_seconds > 0 ? summary.wire_bytes * 8 / summary.stream_seconds / 1000 : 0.0,
      sent.sent, sent.offered, sent.skipped_known, sent.skipped_budget, sent.thinned_budget,
      sent.sent ? static_cast<double>(sent.points_out) / sent.sent : 0.0,
      sent.sent ? summary.payload_bytes / 1024.0 / sent.sent : 0.0);
  return summary.publish_errors == 0 ? 0 : 1;
}
