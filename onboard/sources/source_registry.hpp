// Every frame source stereomap-onboard can read, in one table: the --source prefix, its usage
// and help text, and its opener. The flag's help, its errors and the dispatch all come from the
// table, so a new source is one file (onboard/camera, onboard/sim) and one row here.
//
//   auto opened = openSource("euroc:/data/V1_01", {.max_frames = 100});
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "common/result.hpp"
#include "onboard/camera/frame_source.hpp"

namespace stereomap::sources {

// What stereomap-onboard's flags say about the source; each source takes what applies to it.
struct SourceOptions {
  uint64_t max_frames = 0;  // 0: all (the simulated room's flight loops until stopped)
  double rate_hz = 10.0;    // frame rate of sources without a clock of their own
  std::optional<std::filesystem::path> calibration_file;  // replaces a data set's own
  // The simulator's: the room or deck's seed, and its camera model (a preset name, "" for the
  // source's default, then the read noise and defocus blur when given).
  uint32_t seed = 1;
  // The simulators: seconds into the flight to begin (sim: its 40 s loop; sim:deck: its 60 s
  // descent, 50 for the final approach); other sources refuse anything but 0.
  double start_s = 0;
  std::string camera_preset;
  std::optional<double> noise_sigma, blur_sigma;
};

struct OpenedSource {
  std::unique_ptr<camera::FrameSource> source;
  // Set when the source's own poses should stand in for odometry unless the operator chose
  // (sim:deck: the scene moves with the deck, and the sim's navigation stands in for
  // GPS/INS): why, for the log.
  std::optional<std::string> prefer_ground_truth;
};

struct SourceKind {
  std::string prefix;  // "sim", "sim:deck", "kitti:"; a prefix ending in ':' takes a location
  std::string usage;   // as the help shows it: "kitti:DIR"
  std::string help;    // what it is, in a few words
  // `location`: what follows the prefix; for a source without one, its name (the prefix).
  std::function<common::Result<OpenedSource>(const std::string& location,
                                             const SourceOptions& options)>
      open;
};

// Every source, in the order the help lists them.
const std::vector<SourceKind>& sourceKinds();

// Opens `spec` ("sim", "kitti:DIR", ...). kInvalidArgument for a spec no source takes (naming
// every one), or one without its location; the source's own error otherwise.
common::Result<OpenedSource> openSource(const std::string& spec, const SourceOptions& options);

// "sim (...), sim:deck (...), kitti:DIR (...), ...": for --source's help.
std::string sourcesHelp();

}  // namespace stereomap::sources
