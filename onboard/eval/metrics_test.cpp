// The evaluator against evo: its published results on evo's example trajectories (within
// 0.5%, as the issue asks; measured agreement is 1e-5 or better) and an independent numpy
// re-computation (../shared/data/trajectories/reference_metrics.json), plus small cases
// whose answers are known exactly.
#include "onboard/eval/metrics.hpp"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <fstream>

#include "testing/data.hpp"

namespace stereomap::eval {
namespace {

using common::Quat;
using common::Rigid3;
using common::Trajectory;
using common::Vec3;
using nlohmann::json;

const auto kTrajectories = testing::kDataDir / "trajectories";

json reference() {
  std::ifstream in(kTrajectories / "reference_metrics.json");
  return json::parse(in);
}

Trajectory load(const std::string& name) {
  auto trajectory = common::readTrajectory(kTrajectories / name);
  EXPECT_TRUE(trajectory.ok()) << trajectory.error().message;
  return trajectory.ok() ? *trajectory : Trajectory{};
}

void expectMatches(const Stats& ours, const json& theirs, double tolerance,
                   const std::string& what) {
  for (const auto& [key, value] : std::vector<std::pair<const char*, double>>{
           {"rmse", ours.rmse}, {"mean", ours.mean}, {"median", ours.median}, {"max", ours.max}}) {
    const double expected = theirs.at(key).get<double>();
    EXPECT_NEAR(value, expected, tolerance * std::abs(expected)) << what << " " << key;
  }
}

TEST(EvoCrossCheck, TumDeskAteMatchesEvo) {
  STEREOMAP_SKIP_WITHOUT(kTrajectories);
  const auto pairs = associate(load("fr2_desk_groundtruth.txt"), load("fr2_desk_ORB.txt"));
  EXPECT_EQ(pairs.ref.size(), 2174u);
  const json ref = reference()["fr2_desk_ORB"];
  const auto se3 = absoluteError(pairs.ref, pairs.est, Alignment::kSe3);
  expectMatches(se3.translation, ref["evo_published"]["stats"], 0.005, "APE SE3 vs evo");
  expectMatches(se3.translation, ref["ape_trans_se3"], 1e-6, "APE SE3 vs numpy");
  const auto sim3 = absoluteError(pairs.ref, pairs.est, Alignment::kSim3);
  expectMatches(sim3.translation, ref["ape_trans_sim3"], 1e-6, "APE Sim3 vs numpy");
  EXPECT_NEAR(sim3.alignment.scale, ref["ape_trans_sim3"]["scale"].get<double>(), 1e-9);
  const auto rpe = relativeError(pairs.ref, pairs.est, pairsByFrames(pairs.ref.size(), 1));
  expectMatches(rpe.translation, ref["rpe_trans_delta_1_frame"], 1e-6, "RPE 1 frame vs numpy");
}

TEST(EvoCrossCheck, KittiOrbAndSptamMatchEvo) {
  STEREOMAP_SKIP_WITHOUT(kTrajectories);
  const Trajectory gt = load("KITTI_00_gt.txt");
  for (const auto& [name, file] : {std::pair{"KITTI_00_ORB", "KITTI_00_ORB.txt"},
                                   std::pair{"KITTI_00_SPTAM", "KITTI_00_SPTAM.txt"}}) {
    const json ref = reference()[name];
    const auto pairs = associateByIndex(gt, load(file));
    ASSERT_EQ(pairs.ref.size(), 4541u);
    const auto se3 = absoluteError(pairs.ref, pairs.est, Alignment::kSe3);
    expectMatches(se3.translation, ref["evo_published"]["ape"]["stats"], 0.005,
                  std::string(name) + " APE vs evo");
    expectMatches(se3.translation, ref["ape_trans_se3"], 1e-6, std::string(name) + " APE vs numpy");
    const auto sim3 = absoluteError(pairs.ref, pairs.est, Alignment::kSim3);
    expectMatches(sim3.translation, ref["ape_trans_sim3"], 1e-6, std::string(name) + " Sim3");
    const auto by_path = pairsByPath(pairs.est, 10.0);
    EXPECT_EQ(by_path.size(), ref["rpe_trans_delta_10_m"]["n"].get<size_t>());
    const auto rpe = relativeError(pairs.ref, pairs.est, by_path);
    expectMatches(rpe.translation, ref["evo_published"]["rpe"]["stats"], 0.005,
                  std::string(name) + " RPE 10 m vs evo");
  }
}

// KITTI's own metric: ORB-SLAM2's paper (Mur-Artal and Tardos 2017, table 2) gives 0.70 %
// and 0.25 deg/100 m for its stereo run on sequence 00; the devkit starts a segment every 10
// frames.
TEST(EvoCrossCheck, KittiDriftOfOrbSlam2MatchesItsPaper) {
  STEREOMAP_SKIP_WITHOUT(kTrajectories);
  const auto pairs = associateByIndex(load("KITTI_00_gt.txt"), load("KITTI_00_ORB.txt"));
  const auto drift = kittiDrift(pairs.ref, pairs.est, defaultDriftLengths(pairs.ref), 10);
  ASSERT_EQ(drift.back().length_m, 0.0);
  EXPECT_NEAR(drift.back().translation_percent, 0.70, 0.01);
  EXPECT_NEAR(drift.back().rotation_deg_per_100m, 0.25, 0.01);
}

Trajectory straightLine(size_t n, double step, double scale = 1.0) {
  Trajectory t;
  for (size_t i = 0; i < n; ++i) {
    t.push_back({static_cast<double>(i), Rigid3{Quat::Identity(), Vec3(scale * step * i, 0, 0)}});
  }
  return t;
}

TEST(Metrics, UmeyamaRecoversASimilarity) {
  std::vector<Vec3> src = {{0, 0, 0}, {1, 0, 0}, {0, 2, 0}, {0, 0, 3}, {1, 1, 1}};
  const Quat q(Eigen::AngleAxisd(0.7, Vec3(1, 2, 3).normalized()));
  std::vector<Vec3> dst;
  for (const auto& p : src) dst.push_back(2.5 * (q * p) + Vec3(1, -2, 0.5));
  const auto a = umeyama(src, dst, true);
  EXPECT_NEAR(a.scale, 2.5, 1e-9);
  EXPECT_NEAR(a.rotation.angularDistance(q), 0, 1e-9);
  EXPECT_NEAR((a.translation - Vec3(1, -2, 0.5)).norm(), 0, 1e-9);
}

TEST(Metrics, KittiDriftOfAScaledEstimate) {
  const Trajectory gt = straightLine(101, 1.0);         // 100 m straight
  const Trajectory est = straightLine(101, 1.0, 1.02);  // 2% too long
  const auto drift = kittiDrift(gt, est, {10, 20});
  ASSERT_EQ(drift.size(), 3u);
  EXPECT_EQ(drift[0].segments, 91u);
  EXPECT_EQ(drift[1].segments, 81u);
  for (const auto& d : drift) {
    EXPECT_NEAR(d.translation_percent, 2.0, 1e-9);
    EXPECT_NEAR(d.rotation_deg_per_100m, 0.0, 1e-9);
  }
  EXPECT_EQ(defaultDriftLengths(gt), (std::vector<double>{10, 20, 30, 40, 50}));
  const auto ape = absoluteError(gt, est, Alignment::kSim3);
  EXPECT_NEAR(ape.translation.max, 0, 1e-9);
  EXPECT_NEAR(ape.alignment.scale, 1 / 1.02, 1e-9);
}

TEST(Metrics, AssociationKeepsNearestStampsWithinTheLimit) {
  Trajectory ref = straightLine(5, 1.0), est;
  for (double t : {0.004, 1.02, 2.0, 2.009, 3.5}) est.push_back({t, {}});
  const auto pairs = associate(ref, est, 0.01);
  ASSERT_EQ(pairs.ref.size(), 2u);  // 0 <- 0.004, 2 <- 2.0; 1.02 and 3.5 too far
  EXPECT_DOUBLE_EQ(pairs.ref[0].t, 0.0);
  EXPECT_DOUBLE_EQ(pairs.est[1].t, 2.0);
  EXPECT_NEAR(pairs.max_abs_dt, 0.004, 1e-12);
}

TEST(Trajectories, BadFilesNameTheLine) {
  const auto path = std::filesystem::temp_directory_path() / "stereomap-bad-trajectory.txt";
  common::writeText(path, "# comment\n0 1 2 3 0 0 0 1\n1 1 2 3 0 0 0\n").value();
  auto read = common::readTrajectory(path);
  ASSERT_FALSE(read.ok());
  EXPECT_NE(read.error().message.find(":3: 7 numbers where earlier lines have 8"),
            std::string::npos)
      << read.error().message;
  common::writeText(path, "0 1 2 3 0 0 0 2\n").value();
  EXPECT_NE(common::readTrajectory(path).error().message.find("not unit"), std::string::npos);
  common::writeText(path, "0 1 2 3 0 0 0 nan\n").value();
  EXPECT_FALSE(common::readTrajectory(path).ok());
  // Round trips in both formats.
  const Trajectory line = straightLine(3, 0.5);
  common::writeText(path, common::kittiText(line)).value();
  common::TrajectoryFormat format;
  auto kitti = common::readTrajectory(path, {}, &format);
  ASSERT_TRUE(kitti.ok());
  EXPECT_EQ(format, common::TrajectoryFormat::kKitti);
  EXPECT_NEAR(kitti->at(2).pose.translation.x(), 1.0, 1e-9);
  std::filesystem::remove(path);
}

}  // namespace
}  // namespace stereomap::eval
