// Every stereomap binary as a newcomer meets it: --help answers and exits 0, bad usage says
// what is wrong and exits 2 (STYLE.md). And stereomap-eval end to end on two small TUM files,
// whose errors are known.
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <vector>

#include "tests/support/process.hpp"

namespace stereomap::testing {
namespace {

namespace fs = std::filesystem;

std::string binary(const std::string& name) { return std::string(STEREOMAP_BIN_DIR) + "/" + name; }

TEST(Cli, EveryBinaryHelpsAndRefusesBadUsageWithExitTwo) {
  for (const char* name : {"stereomap-onboard", "stereomap-server", "stereomap-store",
                           "stereomap-eval", "stereomap-calibrate", "stereomap-depth",
                           "stereomap-landing-eval", "stereomap-posegraph"}) {
    const auto help = runTool({binary(name), "--help"});
    EXPECT_EQ(help.exit_code, 0) << name << ": " << help.output;
    EXPECT_NE(help.output.find(name), std::string::npos) << help.output;
    const auto bad = runTool({binary(name), "--no-such-flag"});
    EXPECT_EQ(bad.exit_code, 2) << name << ": " << bad.output;
    // What is wrong (the flag, or a missing subcommand or option, which CLI11 checks first).
    EXPECT_NE(bad.output.find("Run with --help for more information"), std::string::npos)
        << bad.output;
  }
}

// A graph file needs a graph: said at once, not after the flight.
TEST(Cli, GraphOutNeedsThePoseGraph) {
  const auto run = runTool({binary("stereomap-onboard"), "--no-publish", "--frames", "1",
                            "--graph-out", makeTempDir("stereomap-cli-graph") + "/g.g2o"});
  EXPECT_EQ(run.exit_code, 2) << run.output;
  EXPECT_NE(run.output.find("--pose-graph"), std::string::npos) << run.output;
}

// Options that are "auto" or a number refuse what is neither, however it is written, with exit 2
// and a message (not a crash: std::stoi on "nan" or "99999999999" aborted the vehicle).
TEST(Cli, AutoOrNumberOptionsRefuseWhatIsNeither) {
  // stereomap-depth checks its image files exist first: empty ones (unreadable: exit 1 after
  // the flags are taken).
  const fs::path dir = makeTempDir("stereomap-cli-auto");
  const std::string image = (dir / "empty.png").string();
  std::ofstream{image};
  for (const std::string& range :
       std::vector<std::string>{"nan", "inf", "1e400", "1e-300", "12x", "-5", "0"}) {
    const auto run = runTool(
        {binary("stereomap-onboard"), "--max-range", range, "--no-publish", "--frames", "1"});
    EXPECT_EQ(run.exit_code, 2) << "--max-range '" << range << "': " << run.output;
    EXPECT_NE(run.output.find("--max-range"), std::string::npos) << run.output;
    const auto depth = runTool({binary("stereomap-depth"), "--left", image, "--right", image,
                                "--disparity-out", (dir / "d.png").string(), "--max-range", range});
    EXPECT_EQ(depth.exit_code, 2) << "stereomap-depth --max-range '" << range << "'";
  }
  const auto taken = runTool({binary("stereomap-depth"), "--left", image, "--right", image,
                              "--disparity-out", (dir / "d.png").string(), "--max-range", "30"});
  EXPECT_EQ(taken.exit_code, 1) << taken.output;  // the flags were fine, the images are not
  for (const std::string& count : std::vector<std::string>{"nan", "99999999999", "17", "8", "1040",
                                                           "32.5", std::string(5000, '9')}) {
    const auto run = runTool(
        {binary("stereomap-onboard"), "--disparities", count, "--no-publish", "--frames", "1"});
    EXPECT_EQ(run.exit_code, 2) << "--disparities '" << count << "': " << run.output;
  }
}

// The estimate is the truth moved 1 m along x and with every 10th pose 0.1 m off in y: the
// ATE without alignment, the ATE after it and the RPE are known in closed form.
TEST(Cli, EvalMeasuresWhatItIsGiven) {
  const fs::path dir = makeTempDir("stereomap-cli");
  std::ofstream gt(dir / "gt.tum"), est(dir / "est.tum");
  for (int i = 0; i < 100; ++i) {
    const double t = i * 0.1, x = i * 0.5;
    gt << t << " " << x << " 0 0 0 0 0 1\n";
    est << t << " " << x + 1.0 << " " << (i % 10 == 0 ? 0.1 : 0.0) << " 0 0 0 0 1\n";
  }
  gt.close();
  est.close();
  auto eval = [&](std::vector<std::string> args) {
    args.insert(args.begin(), binary("stereomap-eval"));
    args.insert(args.end(), {(dir / "gt.tum").string(), (dir / "est.tum").string(), "--json"});
    const auto run = runTool(args);
    EXPECT_EQ(run.exit_code, 0) << run.output;
    return nlohmann::json::parse(run.output.substr(run.output.find('{')));
  };
  const auto raw = eval({"ate", "--no-align"});
  EXPECT_EQ(raw["pairs"], 100);
  // Each error is 1 m, or sqrt(1 + 0.01) m for every 10th pose.
  EXPECT_NEAR(raw["translation_m"]["max"].get<double>(), std::sqrt(1.01), 1e-9);
  EXPECT_NEAR(raw["translation_m"]["min"].get<double>(), 1.0, 1e-9);
  // Aligned, the shift is gone: what stays is the y offsets' spread around their mean
  // (0.01 m): sqrt(0.1 * 0.09^2 + 0.9 * 0.01^2) = 0.03 m.
  const auto aligned = eval({"ate"});
  EXPECT_NEAR(aligned["translation_m"]["rmse"].get<double>(), 0.03, 1e-3);
  // Frame to frame, the off poses add 0.1 m going and 0.1 m coming back.
  const auto rpe = eval({"rpe", "--delta", "1"});
  EXPECT_NEAR(rpe["translation_m"]["max"].get<double>(), 0.1, 1e-9);
  EXPECT_NEAR(rpe["translation_m"]["min"].get<double>(), 0.0, 1e-9);

  const auto missing = runTool(
      {binary("stereomap-eval"), "ate", (dir / "gt.tum").string(), (dir / "nope.tum").string()});
  EXPECT_EQ(missing.exit_code, 2) << missing.output;  // CLI11's ExistingFile: bad usage
  fs::remove_all(dir);
}

}  // namespace
}  // namespace stereomap::testing
