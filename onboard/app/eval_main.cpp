// stereomap-eval: how good is a trajectory? ATE, RPE and KITTI drift of an estimate against
// ground truth, from TUM or KITTI files, as numbers (text or --json) and as a picture.
#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include <cstdio>
#include <iostream>
#include <utility>
#include <vector>

#include "common/cli.hpp"
#include "onboard/eval/metrics.hpp"
#include "onboard/eval/plot.hpp"

namespace {

using namespace stereomap;
using nlohmann::json;

json statsJson(const eval::Stats& s) {
  return {{"n", s.n},     {"rmse", s.rmse}, {"mean", s.mean}, {"median", s.median},
          {"std", s.std}, {"min", s.min},   {"max", s.max},   {"sse", s.sse}};
}

void printStats(const char* what, const eval::Stats& s, const char* unit) {
  std::printf("%-26s rmse %.6f  mean %.6f  median %.6f  max %.6f %s  (n %zu)\n", what, s.rmse,
              s.mean, s.median, s.max, unit, s.n);
}

struct Inputs {
  std::string gt, est, gt_times, est_times;
  double max_dt = 0.01;
  bool by_index = false;  // set by load(): two KITTI files without times
};

// Reads both files and pairs their poses: by index when both are KITTI files without times,
// by time otherwise.
common::Result<eval::Associated> load(Inputs& in) {
  common::TrajectoryFormat gt_format, est_format;
  auto gt = common::readTrajectory(in.gt, in.gt_times, &gt_format);
  if (!gt) return gt.error();
  auto est = common::readTrajectory(in.est, in.est_times, &est_format);
  if (!est) return est.error();
  const bool by_index = gt_format == common::TrajectoryFormat::kKitti &&
                        est_format == common::TrajectoryFormat::kKitti && in.gt_times.empty() &&
                        in.est_times.empty();
  in.by_index = by_index;
  if (by_index && gt->size() != est->size()) {
    std::fprintf(stderr, "note: %zu reference and %zu estimated poses; comparing the first %zu\n",
                 gt->size(), est->size(), std::min(gt->size(), est->size()));
  }
  auto pairs = by_index ? eval::associateByIndex(*gt, *est) : eval::associate(*gt, *est, in.max_dt);
  if (pairs.ref.size() < 2) {
    return common::makeError(
        common::ErrorCode::kInvalidArgument,
        "only " + std::to_string(pairs.ref.size()) + " poses could be paired (stamps within " +
            std::to_string(in.max_dt) + " s; KITTI files pair by line): are these the same run?");
  }
  return pairs;
}

// Every flag of the three subcommands.
struct Args {
  Inputs in;
  bool as_json = false, scale = false, no_align = false;
  std::string plot;
  double delta = 1;
  std::string unit = "f";
  std::vector<double> lengths;
  size_t step = 1;
};

// ATE after alignment, and the plot when asked; adds its figures to `out`. The exit code.
int absoluteError(const Args& a, const eval::Associated& pairs, json& out) {
  const auto alignment = a.no_align ? eval::Alignment::kNone
                         : a.scale  ? eval::Alignment::kSim3
                                    : eval::Alignment::kSe3;
  const auto result = eval::absoluteError(pairs.ref, pairs.est, alignment);
  const char* name = a.no_align ? "none" : a.scale ? "sim3" : "se3";
  out["alignment"] = name;
  out["scale"] = result.alignment.scale;
  out["translation_m"] = statsJson(result.translation);
  out["rotation_deg"] = statsJson(result.rotation);
  if (!a.plot.empty()) {
    char title[160];
    std::snprintf(title, sizeof(title), "ATE (%s alignment): rmse %.4f m, max %.4f m, %zu poses",
                  name, result.translation.rmse, result.translation.max, result.translation.n);
    if (auto written = common::writeText(
            a.plot,
            eval::plotPng(pairs.ref, result.aligned_est, result.errors, title, a.in.by_index));
        !written) {
      std::fprintf(stderr, "error: %s\n", written.error().message.c_str());
      return 1;
    }
  }
  if (!a.as_json) {
    std::printf("ATE, %s alignment (scale %.6f), %zu pose pairs:\n", name, result.alignment.scale,
                pairs.ref.size());
    printStats("  translation", result.translation, "m");
    printStats("  rotation", result.rotation, "deg");
  }
  return 0;
}

int relativeError(const Args& a, const eval::Associated& pairs, json& out) {
  const auto index_pairs =
      a.unit == "m" ? eval::pairsByPath(pairs.est, a.delta)
                    : eval::pairsByFrames(pairs.ref.size(), static_cast<size_t>(a.delta));
  const auto result = eval::relativeError(pairs.ref, pairs.est, index_pairs);
  out["delta"] = a.delta;
  out["unit"] = a.unit;
  out["translation_m"] = statsJson(result.translation);
  out["rotation_deg"] = statsJson(result.rotation);
  if (!a.as_json) {
    std::printf("RPE, delta %g %s, %zu pairs:\n", a.delta, a.unit == "m" ? "m" : "frames",
                index_pairs.size());
    printStats("  translation", result.translation, "m");
    printStats("  rotation", result.rotation, "deg");
  }
  return 0;
}

int kittiDrift(const Args& a, const eval::Associated& pairs, json& out) {
  const auto lengths = a.lengths.empty() ? eval::defaultDriftLengths(pairs.ref) : a.lengths;
  const auto drift = eval::kittiDrift(pairs.ref, pairs.est, lengths, a.step);
  if (drift.empty()) {
    std::fprintf(stderr, "error: no segment fits: the reference path is %.1f m\n",
                 eval::pathLength(pairs.ref));
    return 1;
  }
  json rows = json::array();
  for (const auto& d : drift) {
    rows.push_back({{"length_m", d.length_m},
                    {"segments", d.segments},
                    {"translation_percent", d.translation_percent},
                    {"rotation_deg_per_100m", d.rotation_deg_per_100m}});
  }
  out["reference_path_m"] = eval::pathLength(pairs.ref);
  out["drift"] = rows;
  if (!a.as_json) {
    std::printf("KITTI drift over %.1f m of reference path (segment starts every %zu frames):\n",
                eval::pathLength(pairs.ref), a.step);
    for (const auto& d : drift) {
      std::printf(
          "  %-10s %4zu segments  translation %7.3f %%  rotation %7.3f deg/100 m\n",
          d.length_m > 0 ? (std::to_string(static_cast<int>(d.length_m)) + " m").c_str() : "all",
          d.segments, d.translation_percent, d.rotation_deg_per_100m);
    }
  }
  return 0;
}

using Measure = int (*)(const Args&, const eval::Associated&, json&);

// The subcommands, each with the measure it runs.
std::vector<std::pair<CLI::App*, Measure>> addCommands(CLI::App& app, Args& a) {
  app.require_subcommand(1);
  auto common_flags = [&](CLI::App* cmd) {
    cmd->add_option("gt", a.in.gt, "Ground truth (TUM: t tx ty tz qx qy qz qw; KITTI: 12 numbers)")
        ->required()
        ->check(CLI::ExistingFile);
    cmd->add_option("est", a.in.est, "Estimate, same formats")
        ->required()
        ->check(CLI::ExistingFile);
    cmd->add_option("--gt-times", a.in.gt_times, "KITTI times.txt for a KITTI ground truth")
        ->check(CLI::ExistingFile);
    cmd->add_option("--est-times", a.in.est_times, "KITTI times.txt for a KITTI estimate")
        ->check(CLI::ExistingFile);
    cmd->add_option("--max-dt", a.in.max_dt, "Largest stamp difference of a pose pair, s")
        ->capture_default_str();
    cmd->add_flag("--json", a.as_json, "Print JSON instead of text");
  };
  auto* ate = app.add_subcommand("ate", "Absolute trajectory error after alignment (evo_ape -a)");
  common_flags(ate);
  ate->add_flag("--scale", a.scale, "Align with scale (Sim3, evo's -as) instead of SE3");
  ate->add_flag("--no-align", a.no_align, "Compare as given");
  ate->add_option("--plot", a.plot, "Write a PNG: top view and error over time");
  auto* rpe = app.add_subcommand("rpe", "Relative pose error, not aligned (evo_rpe)");
  common_flags(rpe);
  rpe->add_option("--delta", a.delta, "Pair distance")->capture_default_str();
  rpe->add_option("--unit", a.unit, "f: frames, m: metres travelled (evo's consecutive pairs)")
      ->check(CLI::IsMember({"f", "m"}))
      ->capture_default_str();
  auto* kitti =
      app.add_subcommand("kitti", "KITTI drift: translation % and deg/100 m over segments");
  common_flags(kitti);
  kitti
      ->add_option("--lengths", a.lengths,
                   "Segment lengths, m (default: KITTI's 100..800 that fit, else 10 m steps up "
                   "to half the path)")
      ->delimiter(',');
  kitti->add_option("--step", a.step, "Frames between segment starts")->capture_default_str();
  return {{ate, absoluteError}, {rpe, relativeError}, {kitti, kittiDrift}};
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "stereomap-eval: trajectory error of an estimate against ground truth (TUM or "
      "KITTI pose files), as evo and the KITTI benchmark compute it"};
  Args args;
  const auto commands = addCommands(app, args);
  if (auto exit_code = common::parseCommandLine(app, argc, argv)) return *exit_code;
  auto pairs = load(args.in);
  if (!pairs) {
    std::fprintf(stderr, "error: %s\n", pairs.error().message.c_str());
    return 1;
  }
  json out = {{"pairs", pairs->ref.size()}, {"max_abs_dt", pairs->max_abs_dt}};
  for (const auto& [command, measure] : commands) {
    if (!command->parsed()) continue;
    if (const int code = measure(args, *pairs, out); code != 0) return code;
  }
  if (args.as_json) std::cout << out.dump(2) << "\n";
  return 0;
}
