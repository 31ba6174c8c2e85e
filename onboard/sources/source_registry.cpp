#include "onboard/sources/source_registry.hpp"

#include <sstream>

#include "onboard/camera/dataset_source.hpp"
#include "onboard/camera/prefetch_source.hpp"
#include "onboard/sim/deck.hpp"
#include "onboard/sim/sim_source.hpp"

namespace stereomap::sources {

namespace {

using common::ErrorCode;
using common::makeError;
using common::Result;

// --camera replaces the source's camera model; --image-noise and --image-blur then set its
// read noise and defocus.
void applyCameraModel(const SourceOptions& options, sim::CameraModel& model) {
  if (!options.camera_preset.empty()) {
    if (auto preset = sim::CameraModel::preset(options.camera_preset)) model = *preset;
  }
  if (options.noise_sigma) model.noise_sigma = *options.noise_sigma;
  if (options.blur_sigma) model.blur_sigma = *options.blur_sigma;
}

double simRate(const SourceOptions& options) {
  return options.rate_hz > 0 ? options.rate_hz : 10.0;  // "as fast as possible" still has a clock
}

// The simulator renders the next frame while the vehicle works on this one, as a camera's own
// hardware would: its rendering is not the vehicle's work (nor its frames' latency).
std::unique_ptr<camera::FrameSource> prefetched(std::unique_ptr<camera::FrameSource> sim) {
  return std::make_unique<camera::PrefetchSource>(std::move(sim));
}

// --start within [0, end) seconds of a simulated flight (`what`), or why not.
std::optional<common::Error> startOutside(const SourceOptions& options, double end,
                                          const std::string& what) {
  if (options.start_s >= 0 && options.start_s <= end) return std::nullopt;
  std::ostringstream message;
  message << "--start " << options.start_s << ": " << what << " lasts " << end
          << " s; start from 0 to " << end << " s";
  return makeError(ErrorCode::kInvalidArgument, message.str());
}

Result<OpenedSource> openSim(const std::string& name, const SourceOptions& options) {
  sim::SimSourceOptions sim{.seed = options.seed,
                            .rate_hz = simRate(options),
                            .max_frames = options.max_frames,
                            .start_s = options.start_s};
  if (name == "sim:hall") sim.room_length = 18.0, sim.room_width = 7.0;
  // Past one loop it flies the same again: a start there is a mistake, not a choice.
  if (auto error = startOutside(options, sim.flight.period_s, "the sim's loop")) return *error;
  applyCameraModel(options, sim.render.camera);
  return OpenedSource{prefetched(std::make_unique<sim::SimSource>(sim)), std::nullopt};
}

Result<OpenedSource> openDeck(const std::string&, const SourceOptions& options) {
  sim::DeckSourceOptions deck{.seed = options.seed,
                              .rate_hz = simRate(options),
                              .max_frames = options.max_frames,
                              .start_s = options.start_s};
  if (auto error = startOutside(options, deck.flight.duration_s, "the descent")) return *error;
  applyCameraModel(options, deck.render.camera);
  return OpenedSource{prefetched(std::make_unique<sim::DeckSource>(deck)),
                      "sim:deck: mapped in the deck's frame, poses from the sim's navigation "
                      "relative to the ship (stands in for a ship-relative GPS/INS)"};
}

// A data set's opener as a row's.
template <typename Location>
auto dataset(Result<std::unique_ptr<camera::FrameSource>> (*open)(const Location&,
                                                                  const camera::DatasetOptions&)) {
  return [open](const std::string& location, const SourceOptions& options) -> Result<OpenedSource> {
    if (options.start_s != 0) {
      return makeError(
          ErrorCode::kInvalidArgument,
          "--start: only the simulators (sim, sim:hall, sim:deck) start later; a data set or "
          "camera starts at its first frame");
    }
    camera::DatasetOptions dataset{.calibration_file = options.calibration_file,
                                   .max_frames = options.max_frames,
                                   .rate_hz = options.rate_hz > 0 ? options.rate_hz : 10.0};
    auto source = open(Location(location), dataset);
    if (!source) return source.error();
    return OpenedSource{std::move(source).value(), std::nullopt};
  };
}

bool takesLocation(const SourceKind& kind) { return kind.prefix.back() == ':'; }

}  // namespace

const std::vector<SourceKind>& sourceKinds() {
  static const std::vector<SourceKind> kinds = {
      {"sim", "sim", "the simulated room's flight", openSim},
      {"sim:hall", "sim:hall",
       "the same flight in another place, a hall of 18 x 7 m (no map of sim overlaps it)", openSim},
      {"sim:deck", "sim:deck", "a descent onto a moving ship's deck with the landing pad",
       openDeck},
      {"kitti:", "kitti:DIR", "a KITTI odometry sequence", dataset(camera::openKitti)},
      {"euroc:", "euroc:DIR", "a EuRoC sequence, ASL layout", dataset(camera::openEuroc)},
      {"folder:", "folder:DIR", "left/right image pairs and a calibration file",
       dataset(camera::openFolder)},
      {"camera:", "camera:LEFT,RIGHT", "two video devices, numbers or paths; needs --calib",
       dataset(camera::openCameras)},
  };
  return kinds;
}

std::string sourcesHelp() {
  std::string text;
  for (const auto& kind : sourceKinds()) {
    text += (text.empty() ? "" : ", ") + kind.usage + " (" + kind.help + ")";
  }
  return text;
}

Result<OpenedSource> openSource(const std::string& spec, const SourceOptions& options) {
  std::string usages;
  for (const auto& kind : sourceKinds()) usages += (usages.empty() ? "" : ", ") + kind.usage;
  for (const auto& kind : sourceKinds()) {
    if (!takesLocation(kind)) {
      if (spec == kind.prefix) return kind.open(spec, options);  // the name: sim or sim:hall
      continue;
    }
    if (spec.rfind(kind.prefix, 0) != 0) continue;
    const std::string location = spec.substr(kind.prefix.size());
    if (location.empty()) {
      return makeError(ErrorCode::kInvalidArgument,
                       "source '" + spec + "' needs a location: " + kind.usage);
    }
    return kind.open(location, options);
  }
  // "kitti" without its colon is a location forgotten, not an unknown source.
  for (const auto& kind : sourceKinds()) {
    if (takesLocation(kind) && spec + ":" == kind.prefix) {
      return makeError(ErrorCode::kInvalidArgument,
                       "source '" + spec + "' needs a location: " + kind.usage);
    }
  }
  return makeError(ErrorCode::kInvalidArgument, "unknown source '" + spec + "': use " + usages);
}

}  // namespace stereomap::sources
