// stereomap-onboard: the vehicle side. Reads stereo frames from a source, estimates its pose
// by stereo visual odometry, computes depth, and streams compressed clouds and poses to
// stereomap-server over DDS. With --no-publish it runs the odometry alone (trajectory files,
// a progress bar and a summary).
#include <spdlog/spdlog.h>
#include <CLI/CLI.hpp>

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "common/cli.hpp"
#include "common/shutdown.hpp"
#include "common/trajectory.hpp"
#include "onboard/link/cloud_link.hpp"
#include "onboard/pipeline/pipeline.hpp"
#include "onboard/sources/source_registry.hpp"
#include "proto/dds_cli.hpp"
#include "proto/wire_size.hpp"

namespace {

using namespace stereomap;

// The map's resolution as the vehicle knows it (--map-resolution); when clouds go whole (0) it
// does not, and the server's default (0.1 m) stands in for the depth range.
double mapResolution(const link::CloudLinkOptions& link) {
  return link.map_resolution_m > 0 ? link.map_resolution_m : 0.1;
}

std::string defaultSessionName() {
  const std::time_t now = std::time(nullptr);
  char text[32];
  std::strftime(text, sizeof(text), "sim-%Y%m%d-%H%M%S", std::gmtime(&now));
  return text;
}

// The command line as given; pipelineOptions() and sourceOptions() turn it into settings.
struct Flags {
  std::string source = "sim";
  std::string calibration_file;
  uint64_t frames = 0;
  double rate_hz = 10.0;
  pipeline::PipelineOptions pipeline;
  proto::DdsOptions dds;
  uint32_t seed = 1;
  double start_s = 0;
  std::string frame = "session", start_pose = "0,0,0,0";
  std::string stereo_preset = "fast", noise_handling = "auto", codec = "auto";
  std::string camera_preset;
  double noise_sigma = 0, blur_sigma = 0;
  std::string vo = "fast";
  std::string trajectory_out, kitti_out, odometry_out, truth_out, graph_out;
  bool no_publish = false;
  double wait_s = 3.0;
  double paper_resolution = 0;
  std::string landing_mode = "off";
  // The low end of drone radio links (1-10 Mbit/s): a real rig's clouds fit it by default.
  std::string link_budget = "1Mbit";
  std::string max_range = "auto", disparities = "auto";
  // Where unacknowledged samples are kept: auto (a folder per vehicle id under the user's state
  // folder), a folder, memory, or off (no acknowledgements: sent once).
  std::string spool = "auto";
  link::SpoolOptions spool_options;
  double resend_after_s = 3.0;
  double flush_timeout_s = 5.0;
  bool skip_late = true;
  bool keep_when_closed = true;  // --on-closed
  double link_bits_per_s = 0;    // --link-budget, parsed
};

void addFlags(CLI::App& app, Flags& f) {
  f.pipeline.session_id = defaultSessionName();
  app.add_option("--source", f.source, "Frame source: " + sources::sourcesHelp())
      ->capture_default_str();
  app.add_option("--calib", f.calibration_file,
                 "Stereo calibration (ours, OpenCV stereo_calib, KITTI calib.txt); overrides "
                 "the source's own")
      ->check(CLI::ExistingFile);
  app.add_option("--frames", f.frames,
                 "Stop after N frames (0: until a recording's last frame, else until Ctrl-C)")
      ->capture_default_str();
  app.add_option("--start", f.start_s,
                 "The simulators: seconds into the flight to begin; sim: into its 40 s loop, "
                 "sim:deck: into its 60 s descent (52: the last 5.3 m, the final approach)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  app.add_option("--rate", f.rate_hz, "Frames per second (0: as fast as possible)")
      ->check(CLI::Range(0.0, 1000.0))
      ->capture_default_str();
  app.add_option("--session", f.pipeline.session_id, "Session name (letters, digits, . _ -)")
      ->capture_default_str();
  app.add_option("--vehicle", f.pipeline.vehicle_id, "Vehicle id")->capture_default_str();
  app.add_option("--frame", f.frame,
                 "The frame poses and clouds are sent in: session (the source's map, shared by "
                 "the session's vehicles) or own (the vehicle's own, fixed at its first pose, "
                 "which is sent as --start-pose; the server holds its clouds apart until it has "
                 "aligned its map into the session's)")
      ->check(CLI::IsMember({"session", "own"}))
      ->capture_default_str();
  app.add_option("--start-pose", f.start_pose,
                 "With --frame own: the first pose sent, x,y,z,yaw_deg (metres, degrees about "
                 "+z; no roll or pitch)")
      ->capture_default_str();
  proto::addDdsFlags(app, f.dds);
  app.add_option("--seed", f.seed, "Simulated room's seed")->capture_default_str();
  app.add_option("--stereo", f.stereo_preset,
                 "Stereo configuration: fast (real time) or accurate (docs/BENCHMARKS.md)")
      ->check(CLI::IsMember({"fast", "accurate"}))
      ->capture_default_str();
  app.add_option("--noise-handling", f.noise_handling,
                 "Image noise in the depth step: auto (estimated from the images; noisy "
                 "images are matched smoothed with larger blocks and their depth averaged over "
                 "frames, docs/BENCHMARKS.md), on (always so) or off (frame by frame, as for "
                 "clean images)")
      ->check(CLI::IsMember({"auto", "on", "off"}))
      ->capture_default_str();
  app.add_option("--max-range", f.max_range,
                 "Farthest depth mapped, metres, or auto: from the calibration, the map's "
                 "resolution and the matcher's precision (where a disparity error moves a point "
                 "by less than a voxel); said at the start")
      ->check(common::autoOr(0.5, 100.0))
      ->capture_default_str();
  app.add_option("--disparities", f.disparities,
                 "Disparity search, a multiple of 16 from the far limit's disparity, or auto: a "
                 "pyramid of windows from the far limit to the rig's nearest depth (a quarter of "
                 "the image width of disparity), nearer ones on halved images")
      ->check(common::autoOr(16, 1024, 16))
      ->capture_default_str();
  app.add_option("--codec", f.codec,
                 "Cloud encoding: auto (the smallest, docs/BENCHMARKS.md: draco for clouds "
                 "thinned to the map's voxels, zstd for whole ones), draco (kd-tree), zstd "
                 "(quantised, delta coded, zstd) or raw (floats)")
      ->check(CLI::IsMember({"auto", "draco", "zstd", "raw"}))
      ->capture_default_str();
  app.add_option("--quantization-bits", f.pipeline.codec.quantization_bits,
                 "Position quantisation bits (draco and zstd); thinned clouds use fewer when "
                 "1/64 of a voxel allows")
      ->check(CLI::Range(6, 20))
      ->capture_default_str();
  app.add_option("--camera", f.camera_preset,
                 "Sim: the camera model: clean (exact images; the room's default), typical "
                 "(noise sigma 2 at mid grey, 5 % left/right gain mismatch, defocus, motion "
                 "blur, vignetting, gamma) or poor (sigma 4, 10 %, stronger blur); the deck's "
                 "default is typical. --image-noise and --image-blur "
                 "override its read noise and defocus")
      ->check(CLI::IsMember({"clean", "typical", "poor"}));
  app.add_option("--image-noise", f.noise_sigma, "Sim: Gaussian image noise, grey levels")
      ->check(CLI::Range(0.0, 50.0))
      ->capture_default_str();
  app.add_option("--image-blur", f.blur_sigma, "Sim: Gaussian blur of the images, pixels")
      ->check(CLI::Range(0.0, 10.0))
      ->capture_default_str();
  app.add_option("--vo", f.vo,
                 "Pose from: fast (stereo visual odometry), paper (the stereo-VO paper's "
                 "method) or gt (the source's ground truth)")
      ->check(CLI::IsMember({"fast", "paper", "gt"}))
      ->capture_default_str();
  app.add_option("--trajectory-out", f.trajectory_out,
                 "Write the poses (T_map_body) as TUM: t tx ty tz qx qy qz qw, in the frame "
                 "sent (--frame); with --pose-graph, every frame through the final graph");
  auto* pose_graph =
      app.add_flag("--pose-graph", f.pipeline.pose_graph,
                   "Correct the odometry with a pose graph over its keyframes: loop closures and "
                   "joins of lost tracks by place recognition, solved on a worker thread; the "
                   "corrected keyframe poses are sent to the server, which fuses its map again");
  app.add_option("--graph-out", f.graph_out,
                 "Write the final keyframe graph as g2o (VERTEX_SE3:QUAT: each keyframe's left "
                 "camera in the odometry's world frame as solved; EDGE_SE3:QUAT: odometry, "
                 "joins and loops with their information, in the convention Ceres' example "
                 "and stereomap-posegraph read)")
      ->needs(pose_graph);
  app.add_option("--odometry-trajectory-out", f.odometry_out,
                 "Write the odometry's own poses (T_map_body, TUM, in the frame sent), before "
                 "any correction");
  app.add_option("--truth-out", f.truth_out,
                 "Write the source's ground-truth poses (T_map_body, TUM), where it has them, "
                 "at the stamps sent; in the source's frame, also with --frame own");
  app.add_option("--kitti-poses-out", f.kitti_out,
                 "Write the left camera's poses relative to the first frame, KITTI format");
  app.add_flag("--no-publish", f.no_publish,
               "No DDS: run the odometry alone (with a progress bar and a summary)");
  app.add_option("--voxel-downsample", f.pipeline.stereo.cloud.voxel_m,
                 "Keep one point per voxel of this edge, metres (0: off; the 5x2 blocks stay)")
      ->check(CLI::Range(0.0, 10.0))
      ->capture_default_str();
  app.add_option("--min-disparity-for-resolution", f.paper_resolution,
                 "Skip disparities below the octree-mapping paper's d_min = ceil(sqrt(b*f*0.5/r)) "
                 "for map resolution r metres (0: off)")
      ->check(CLI::Range(0.0, 10.0));
  app.add_option("--landing", f.landing_mode,
                 "Watch for the landing pad and publish it (LandingTarget): default (PnP refined "
                 "on both images) or patent (the patent's linear solution); off: no watch")
      ->check(CLI::IsMember({"off", "default", "patent"}))
      ->capture_default_str();
  app.add_option("--link-budget", f.link_budget,
                 "Keep the stream under this rate on the radio link (1Mbit, 500kbit, ...; off: "
                 "no limit): clouds go out thinner, or are skipped, poses keep their rate")
      ->capture_default_str();
  auto& link = *f.pipeline.link;
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
  app.add_option("--spool", f.spool,
                 "Where samples the server has not acknowledged are kept, to send again after "
                 "an outage of any length or a restart: auto ($STEREOMAP_SPOOL, else "
                 "~/.local/state/stereomap/spool/VEHICLE; memory when another process has it), a "
                 "folder, memory (lost with the process), or off (each sample sent once; DDS "
                 "keeps a few seconds)")
      ->capture_default_str();
  app.add_option("--spool-max", f.spool_options.max_bytes,
                 "Most the spool holds (256MB: 3 hours of the default thinned stream, 34 min of a "
                 "full 1 Mbit/s); when full the oldest clouds are given up first, poses and "
                 "session events last")
      ->transform(CLI::AsSizeValue(false))
      ->capture_default_str();
  app.add_option("--spool-memory", f.spool_options.memory_bytes,
                 "Of it, held in memory too; older samples are read back from the spool's files")
      ->transform(CLI::AsSizeValue(false))
      ->capture_default_str();
  app.add_option("--skip-late", f.skip_late,
                 "A live source (a camera, the sim at --rate) that the vehicle cannot keep up "
                 "with skips to the newest frame (on: poses stay live) or queues every frame "
                 "(off: each one taken, late); recorded data sets keep every frame either way")
      ->transform(
          CLI::CheckedTransformer(std::map<std::string, bool>{{"on", true}, {"off", false}}))
      ->default_str("on");
  app.add_option("--on-closed", f.keep_when_closed,
                 "When the server says the session was closed (an operator closed it, or "
                 "opened it read-only): the vehicle says so once and sends nothing more to it; "
                 "keep: what the spool holds, and what the vehicle makes after, stay in the "
                 "spool; drop: they are given up (counted)")
      ->transform(
          CLI::CheckedTransformer(std::map<std::string, bool>{{"keep", true}, {"drop", false}}))
      ->default_str("keep");
  app.add_option("--flush-timeout", f.flush_timeout_s,
                 "Seconds to wait at the end for the server to acknowledge everything sent (what "
                 "is left stays in the spool for the next run on it)")
      ->check(CLI::Range(0.0, 3600.0))
      ->capture_default_str();
  app.add_option("--resend-after", f.resend_after_s,
                 "Seconds without an acknowledgement before a sample is sent again")
      ->check(CLI::Range(0.2, 3600.0))
      ->capture_default_str();
  app.set_config("--config", "", "Read these options from a TOML or INI file (name = value)");
  app.allow_config_extras(CLI::config_extras_mode::error);  // a typo in the file is an error
  app.add_option("--wait-for-server", f.wait_s, "Seconds to wait for a server before streaming")
      ->check(CLI::Range(0.0, 600.0))
      ->capture_default_str();
}

// --start-pose's "x,y,z,yaw_deg" as T_own_body; nullopt for anything else.
std::optional<common::Rigid3> parseStartPose(const std::string& text) {
  std::vector<double> values;
  std::string rest = text;
  for (size_t comma = 0; comma != std::string::npos && values.size() <= 4;) {
    comma = rest.find(',');
    const auto value = common::autoOrNumber(rest.substr(0, comma));
    if (!value) return std::nullopt;
    values.push_back(*value);
    rest = comma == std::string::npos ? std::string() : rest.substr(comma + 1);
  }
  if (values.size() != 4) return std::nullopt;
  const double yaw_rad = values[3] * M_PI / 180.0;
  return common::Rigid3{common::Quat(Eigen::AngleAxisd(yaw_rad, common::Vec3::UnitZ())),
                        common::Vec3(values[0], values[1], values[2])};
}

// Completes f.pipeline from the flags CLI11 cannot check alone; false (said) on bad usage.
bool pipelineOptions(const CLI::App& app, Flags& f) {
  auto& options = f.pipeline;
  if (f.frame == "own") {
    const auto start_pose = parseStartPose(f.start_pose);
    if (!start_pose) {
      spdlog::error("--start-pose '{}' must be x,y,z,yaw_deg: four numbers, commas between",
                    f.start_pose);
      return false;
    }
    options.frame = proto::VehicleFrame::kOwn;
    options.start_pose = *start_pose;
  } else if (app.count("--start-pose") > 0) {
    spdlog::error(
        "--start-pose needs --frame own (in the session's frame the source's poses go "
        "as they are)");
    return false;
  }
  if (options.session_id.empty() || options.session_id.size() > proto::kMaxIdLength ||
      options.session_id.find_first_not_of("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ"
                                           "0123456789._-") != std::string::npos) {
    spdlog::error("--session '{}' must be 1-64 letters, digits, '.', '_' or '-'",
                  options.session_id);
    return false;
  }
  auto& link = *options.link;
  if (auto budget = link::parseBitRate(f.link_budget); !budget) {
    spdlog::error("--link-budget: {}", budget.error().message);
    return false;
  } else if (*budget > 0) {
    f.link_bits_per_s = *budget;
    proto::PoseMsg pose;
    pose.vehicle_id = options.vehicle_id;
    pose.session_id = options.session_id;
    const double poses =
        static_cast<double>(proto::wireBytes(pose)) * 8 * (f.rate_hz > 0 ? f.rate_hz : 30.0);
    link.budget_bits_per_s = link::cloudShare(*budget, poses);
    if (link.budget_bits_per_s <= 0) {
      spdlog::error("--link-budget {}: the poses alone need {:.0f} kbit/s", f.link_budget,
                    poses / 1000);
      return false;
    }
  }
  options.codec.encoding =
      f.codec == "auto" ? link::bestEncoding(link) : *proto::parseEncoding(f.codec);  // IsMember
  options.rate_hz = f.rate_hz;
  options.skip_late = f.skip_late;
  options.flush_timeout = std::chrono::milliseconds(static_cast<int64_t>(f.flush_timeout_s * 1000));
  options.stereo.matcher = f.stereo_preset == "accurate" ? stereo::MatcherOptions::accurate()
                                                         : stereo::MatcherOptions::fast();
  // The range and the disparity search: from the rig unless given (explicit flags win).
  if (f.disparities != "auto") {
    options.stereo.range.reset();
    // Both checked by common::autoOr.
    options.stereo.matcher.num_disparities = static_cast<int>(*common::autoOrNumber(f.disparities));
    // A far limit given, or the rig's (adaptToSource, once the camera is known).
    if (const auto far = common::autoOrNumber(f.max_range)) options.stereo.cloud.max_range_m = *far;
  } else {
    options.stereo.range =
        stereo::AutoRange{.map_resolution_m = mapResolution(link),
                          .far_m = common::autoOrNumber(f.max_range).value_or(0.0)};
  }
  options.stereo.noise = f.noise_handling == "on"    ? stereo::NoiseHandling::kOn
                         : f.noise_handling == "off" ? stereo::NoiseHandling::kOff
                                                     : stereo::NoiseHandling::kAuto;
  options.wait_for_server = std::chrono::milliseconds(static_cast<int64_t>(f.wait_s * 1000));
  options.depth = !f.no_publish;  // the clouds only matter to a server
  if (f.landing_mode != "off") {
    options.landing = landing::LandingWatchOptions{};
    options.landing->pose.mode =
        f.landing_mode == "patent" ? landing::PoseMode::kPatent : landing::PoseMode::kDefault;
  }
  if (f.no_publish) options.progress_every = 0;
  return true;
}

sources::SourceOptions sourceOptions(const CLI::App& app, const Flags& f) {
  sources::SourceOptions options{.max_frames = f.frames,
                                 .rate_hz = f.rate_hz,
                                 .seed = f.seed,
                                 .start_s = f.start_s,
                                 .camera_preset = f.camera_preset};
  if (!f.calibration_file.empty()) options.calibration_file = f.calibration_file;
  if (app.count("--image-noise") > 0) options.noise_sigma = f.noise_sigma;
  if (app.count("--image-blur") > 0) options.blur_sigma = f.blur_sigma;
  return options;
}

// What the source implies for the pipeline: where poses come from (a source may prefer its
// own when --vo was not given) and the paper's minimum disparity for the camera.
void adaptToSource(const CLI::App& app, const sources::OpenedSource& opened, Flags& f) {
  if (opened.prefer_ground_truth && app.count("--vo") == 0) {
    f.vo = "gt";
    spdlog::info("{} (--vo to change)", *opened.prefer_ground_truth);
  }
  auto& options = f.pipeline;
  options.pose_source =
      f.vo == "gt" ? pipeline::PoseSource::kGroundTruth : pipeline::PoseSource::kOdometry;
  options.odometry.mode = f.vo == "paper" ? odometry::VoMode::kPaper : odometry::VoMode::kFast;
  const auto& camera = opened.source->camera();
  if (!options.stereo.range && f.max_range == "auto") {
    options.stereo.cloud.max_range_m = stereo::farthestMappable(
        camera, mapResolution(*options.link), options.stereo.matcher.precision_px);
  }
  if (f.paper_resolution > 0) {
    const int min_disparity =
        stereo::minimumDisparity(camera.baseline, camera.fx, f.paper_resolution);
    // The paper's rule as the far limit: the rig's windows, or the matcher's own, start there.
    if (options.stereo.range) {
      options.stereo.range->far_m = camera.depthFromDisparity(min_disparity);
    } else {
      options.stereo.matcher.min_disparity = min_disparity;
    }
    spdlog::info("minimum disparity {} px (depth up to {:.2f} m) for {} m voxels", min_disparity,
                 camera.depthFromDisparity(min_disparity), f.paper_resolution);
  }
}

// The trajectory files asked for, kept frame by frame (only when asked: a live vehicle runs
// until Ctrl-C), and a progress bar when the odometry runs alone on a terminal.
class TrajectoryFiles {
 public:
  explicit TrajectoryFiles(const Flags& f) : f_(f), bar_(f.no_publish && isatty(STDERR_FILENO)) {}

  void onFrame(const pipeline::FrameReport& r) {
    const double t = static_cast<double>(r.stamp_ns) * 1e-9;
    ++frames_;
    if (!f_.trajectory_out.empty()) trajectory_.push_back({t, r.T_map_body});
    if (!f_.odometry_out.empty()) odometry_.push_back({t, r.T_map_body_odometry});
    if (!f_.truth_out.empty() && r.T_map_body_truth) truth_.push_back({t, *r.T_map_body_truth});
    if (!first_camera_) first_camera_ = r.T_map_camera;
    if (!f_.kitti_out.empty()) kitti_.push_back({t, first_camera_->inverse() * r.T_map_camera});
    if (bar_) {
      const int filled = f_.frames > 0 ? static_cast<int>(30 * frames_ / f_.frames)
                                       : static_cast<int>(frames_ % 31);
      std::fprintf(stderr, "\r[%-30s] %llu%s frames, odometry %s, %.1f ms",
                   std::string(filled, '#').c_str(), static_cast<unsigned long long>(frames_),
                   f_.frames > 0 ? ("/" + std::to_string(f_.frames)).c_str() : "",
                   odometry::stateName(r.state), r.odometry_ms);
    }
  }

  // Writes the files; with a pose graph, the trajectory as the final graph has it.
  bool write(const pipeline::PipelineSummary& summary) {
    if (bar_) std::fprintf(stderr, "\n");
    if (f_.pipeline.pose_graph && summary.corrected_T_map_body.size() == trajectory_.size()) {
      for (size_t i = 0; i < trajectory_.size(); ++i) {
        trajectory_[i].pose = summary.corrected_T_map_body[i];
      }
    }
    for (const auto& [path, text] : {std::pair{f_.trajectory_out, common::tumText(trajectory_)},
                                     std::pair{f_.kitti_out, common::kittiText(kitti_)},
                                     std::pair{f_.odometry_out, common::tumText(odometry_)},
                                     std::pair{f_.truth_out, common::tumText(truth_)}}) {
      if (path.empty()) continue;
      if (auto written = common::writeText(path, text); !written) {
        spdlog::error("{}", written.error().message);
        return false;
      }
      spdlog::info("wrote {} poses to {}", frames_, path);
    }
    if (!f_.graph_out.empty()) {
      if (auto written = posegraph::writeG2o(f_.graph_out, summary.keyframe_graph); !written) {
        spdlog::error("{}", written.error().message);
        return false;
      }
      spdlog::info("wrote the keyframe graph ({} keyframes, {} edges) to {}",
                   summary.keyframe_graph.vertices.size(), summary.keyframe_graph.edges.size(),
                   f_.graph_out);
    }
    return true;
  }

 private:
  const Flags& f_;
  const bool bar_;
  uint64_t frames_ = 0;
  common::Trajectory trajectory_, kitti_, odometry_, truth_;
  std::optional<common::Rigid3> first_camera_;
};

// The vehicle's DDS writers (nullptr with --no-publish); false (said) when DDS fails.
// The spool --spool asks for: nullptr for off; false (said) when a folder given cannot be used.
// auto falls back to memory (with a warning) when its folder cannot be had.
bool openSpool(const Flags& f, std::unique_ptr<link::Spool>& spool) {
  if (f.spool == "off") return true;
  link::SpoolOptions options = f.spool_options;
  if (f.spool == "auto") {
    if (const char* dir = std::getenv("STEREOMAP_SPOOL"); dir != nullptr && *dir != '\0') {
      options.dir = dir;
    } else if (const char* state = std::getenv("XDG_STATE_HOME"); state != nullptr && *state) {
      options.dir = std::filesystem::path(state) / "stereomap" / "spool" / f.pipeline.vehicle_id;
    } else if (const char* home = std::getenv("HOME"); home != nullptr && *home != '\0') {
      options.dir = std::filesystem::path(home) / ".local" / "state" / "stereomap" / "spool" /
                    f.pipeline.vehicle_id;
    }
  } else if (f.spool != "memory") {
    options.dir = f.spool;
  }
  auto opened = link::Spool::open(options);
  if (!opened && f.spool == "auto") {
    spdlog::warn("spool: {}; keeping unacknowledged samples in memory only",
                 opened.error().message);
    options.dir.clear();
    opened = link::Spool::open(options);
  }
  if (!opened) {
    spdlog::error("--spool: {}", opened.error().message);
    return false;
  }
  spool = std::move(opened).value();
  spdlog::info("spool: {} (up to {} MB){}",
               options.dir.empty() ? std::string("in memory") : options.dir.string(),
               options.max_bytes >> 20,
               spool->empty() ? std::string()
                              : fmt::format(", {} samples left by an earlier run to send again",
                                            spool->stats().held));
  return true;
}

bool makePublisher(const Flags& f, const camera::FrameSource& source,
                   std::shared_ptr<proto::Participant>& participant,
                   std::unique_ptr<pipeline::VehiclePublisher>& publisher) {
  if (f.no_publish) {
    spdlog::info("odometry ({}) on {}, nothing published", f.vo, source.describe());
    return true;
  }
  proto::logSecurityDates(f.dds);
  auto created = proto::Participant::create(f.dds);
  if (!created) {
    spdlog::error("{}", created.error().message);
    return false;
  }
  participant = std::move(created).value();
  std::unique_ptr<link::Spool> spool;
  if (!openSpool(f, spool)) return false;
  const link::OutboxOptions outbox{
      .vehicle_id = f.pipeline.vehicle_id,
      .link_bits_per_s = f.link_bits_per_s,
      .resend_after = std::chrono::milliseconds(static_cast<int64_t>(f.resend_after_s * 1000)),
      .keep_when_closed = f.keep_when_closed};
  auto made = pipeline::VehiclePublisher::create(participant, f.pipeline.session_id,
                                                 std::move(spool), outbox);
  if (!made) {
    spdlog::error("{}", made.error().message);
    return false;
  }
  publisher = std::move(made).value();
  spdlog::info("vehicle '{}' session '{}' on DDS domain {}: {} at {} Hz{}, pose from {}",
               f.pipeline.vehicle_id, f.pipeline.session_id, f.dds.domain_id, source.describe(),
               f.rate_hz,
               f.frames > 0    ? fmt::format(", {} frames", f.frames)
               : source.live() ? std::string(", until Ctrl-C")  // a camera, a simulator
                               : std::string(", until the recording's last frame"),
               f.vo);
  return true;
}

// The summary lines (tests and operators read them); the exit code.
int reportSummary(const Flags& f, const pipeline::PipelineSummary& summary) {
  if (f.pipeline.pose_graph) {
    spdlog::info(
        "pose graph: {} keyframes, {} loop closures, {} of {} later tracks joined, "
        "longest solve {:.1f} ms",
        summary.graph.keyframes, summary.graph.loops, summary.graph.joined_tracks,
        std::max(0, summary.graph.tracks - 1), summary.graph.solve_ms_max);
  }
  if (f.pipeline.pose_source == pipeline::PoseSource::kOdometry) {
    spdlog::info("odometry: {} frames, {} lost, {} degraded, {:.1f} ms per frame (median)",
                 summary.frames, summary.lost_frames, summary.degraded_frames,
                 summary.median_odometry_ms);
    // Half a pixel of disparity bias costs several percent of scale at 20 m.
    if (std::abs(summary.right_offset_px) > 0.5) {
      spdlog::warn(
          "the right image sits {:+.2f} px off its calibration (estimated by the odometry, "
          "which corrects for it); the stereo calibration needs redoing",
          summary.right_offset_px);
    } else if (f.pipeline.odometry.mode == odometry::VoMode::kFast) {
      spdlog::info(
          "stereo calibration check: right image offset {:+.2f} px, right camera gain {:.3f}",
          summary.right_offset_px, summary.right_gain);
    }
  }
  if (f.pipeline.landing) {
    spdlog::info("landing pad: tracked in {} of {} frames, {} poses published",
                 summary.landing_tracked, summary.frames, summary.landing_poses);
  }
  if (f.no_publish) return 0;
  if (!summary.depth_range.empty()) spdlog::info("depth range: {}", summary.depth_range);
  spdlog::info(
      "done: {} frames{}, {} points ({:.0f} per frame), depth {:.1f} ms, encode {:.1f} ms, frame "
      "{:.1f} ms (medians), slowest {:.1f} ms, at most {:.0f} ms behind, {} late, {} publish "
      "errors; images {} (noise sigma {:.1f} grey levels)",
      summary.frames, summary.stopped ? " (stopped)" : "", summary.points,
      summary.frames ? static_cast<double>(summary.points) / summary.frames : 0.0,
      summary.median_depth_ms, summary.median_encode_ms, summary.median_frame_ms,
      summary.slowest_frame_ms, summary.most_behind_ms, summary.late_frames, summary.publish_errors,
      summary.noisy_images ? "noisy" : "clean", summary.image_noise_sigma);
  const auto& sent = summary.link;
  spdlog::info(
      "link: sent {:.0f} kbit/s (clouds and poses), {} of {} clouds ({} skipped with nothing new, "
      "{} empty, {} over the budget, {} thinner for it), {:.0f} points and {:.1f} KiB per cloud "
      "sent{}",
      summary.stream_seconds > 0 ? summary.wire_bytes * 8 / summary.stream_seconds / 1000 : 0.0,
      sent.sent, sent.offered, sent.skipped_known, sent.skipped_empty, sent.skipped_budget,
      sent.thinned_budget, sent.sent ? static_cast<double>(sent.points_out) / sent.sent : 0.0,
      sent.sent ? summary.payload_bytes / 1024.0 / sent.sent : 0.0,
      summary.spool && summary.spool->dropped_clouds > 0
          ? fmt::format(", {} given up by the full spool", summary.spool->dropped_clouds)
          : std::string());
  if (summary.skipped_frames > 0) {
    spdlog::info("live source: {} frames skipped to stay live (the vehicle fell behind its {} Hz)",
                 summary.skipped_frames, f.rate_hz);
  }
  if (summary.outbox && summary.spool) {
    const auto& out = *summary.outbox;
    const auto& spool = *summary.spool;
    spdlog::info(
        "spool: {} samples sent again ({:.0f} KiB), {} still unacknowledged ({:.0f} KiB), {} "
        "clouds and {} other samples given up when full, {} KiB written to disk{}",
        out.resent, out.resent_bytes / 1024.0, spool.held, spool.held_bytes / 1024.0,
        spool.dropped_clouds, spool.dropped_other, spool.disk_bytes / 1024,
        spool.disk_ok ? std::string() : "; disk problem: " + spool.disk_problem);
  }
  if (f.pipeline.frame == proto::VehicleFrame::kOwn) {
    const auto& T = summary.T_session_own;
    switch (summary.frame_state) {
      case proto::FrameState::kAligned:
        spdlog::info("frame: own, aligned, t {:.6f} {:.6f} {:.6f} q {:.6f} {:.6f} {:.6f} {:.6f}",
                     T.translation.x(), T.translation.y(), T.translation.z(), T.rotation.x(),
                     T.rotation.y(), T.rotation.z(), T.rotation.w());
        break;
      case proto::FrameState::kAligning:
        spdlog::info("frame: own, aligning");
        break;
      case proto::FrameState::kNone:
        spdlog::info("frame: own, the server said nothing of its alignment{}",
                     summary.outbox ? "" : " (acknowledgements need a spool: --spool)");
        break;
    }
  }
  if (!summary.closed_by_server.empty()) {
    const uint64_t held_back = summary.outbox ? summary.outbox->held_back : 0;
    const uint64_t dropped = summary.spool ? summary.spool->dropped_closed : 0;
    spdlog::warn(
        "session closed by the server: {}; {} samples not sent after it, {} given up, {} kept in "
        "the spool",
        summary.closed_by_server, held_back, dropped, summary.spool ? summary.spool->held : 0);
    return 3;
  }
  return summary.publish_errors == 0 ? 0 : 1;
}

}  // namespace

int main(int argc, char** argv) {
  common::Shutdown shutdown;  // first: blocks SIGINT/SIGTERM for every later thread

  CLI::App app{"stereomap-onboard: stream a vehicle's stereo depth and pose to the server"};
  Flags flags;
  addFlags(app, flags);
  if (auto exit_code = common::parseCommandLine(app, argc, argv)) return *exit_code;
  if (!pipelineOptions(app, flags)) return 2;

  auto opened = sources::openSource(flags.source, sourceOptions(app, flags));
  if (!opened) {
    spdlog::error("{}", opened.error().message);
    return opened.error().code == common::ErrorCode::kInvalidArgument ? 2 : 1;
  }
  adaptToSource(app, *opened, flags);
  if (flags.pipeline.depth) {
    const stereo::DepthStep depth(opened->source->camera(), flags.pipeline.stereo);
    if (const auto problem = depth.problem(); !problem.empty()) {
      spdlog::error("{}: {}", opened->source->describe(), problem);
      return 1;
    }
  }

  TrajectoryFiles files(flags);
  flags.pipeline.on_frame = [&files](const pipeline::FrameReport& r) { files.onFrame(r); };
  std::shared_ptr<proto::Participant> participant;
  std::unique_ptr<pipeline::VehiclePublisher> publisher;
  if (!makePublisher(flags, *opened->source, participant, publisher)) return 1;

  const auto summary =
      pipeline::runPipeline(*opened->source, publisher.get(), flags.pipeline, shutdown);
  if (!files.write(summary)) return 1;
  return reportSummary(flags, summary);
}
