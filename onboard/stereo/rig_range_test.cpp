#include "onboard/stereo/rig_range.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <optional>
#include <utility>

#include "onboard/sim/renderer.hpp"
#include "onboard/stereo/depth.hpp"
#include "onboard/stereo/depth_step.hpp"
#include "onboard/stereo/disparity_io.hpp"
#include "testing/data.hpp"

namespace stereomap::stereo {
namespace {

using common::Vec3;

camera::StereoCamera rig(int width, int height, double fx, double baseline) {
  camera::StereoCamera camera;
  camera.width = width;
  camera.height = height;
  camera.fx = camera.fy = fx;
  camera.cx = width / 2.0;
  camera.cy = height / 2.0;
  camera.baseline = baseline;
  return camera;
}

// The sim's camera, KITTI's, EuRoC's and a wide aerial rig.
const camera::StereoCamera kRigs[] = {camera::StereoCamera{}, rig(1241, 376, 718.856, 0.5372),
                                      rig(752, 480, 458.0, 0.110), rig(2048, 1536, 2200, 1.0)};

TEST(RigRange, TheFarLimitIsWhereOneDisparityErrorMovesAPointByAVoxel) {
  for (const auto& camera : kRigs) {
    for (const double resolution : {0.05, 0.1, 0.2}) {
      const RigRange range =
          rigRange(camera, {.map_resolution_m = resolution, .precision_px = 0.1});
      // dz = z^2 dd / (b f) (the mapping paper's eq. 4) equals the voxel at the far limit.
      const double bf = camera.baseline * camera.fx;
      EXPECT_NEAR(range.far_m * range.far_m * 0.1 / bf, resolution, 1e-9);
      EXPECT_TRUE(range.far_from_rule);
      // Near: a quarter of the image's width of disparity.
      EXPECT_NEAR(range.near_disparity_px, 0.25 * camera.width, 1e-9);
      EXPECT_LT(range.near_m, range.far_m);
    }
  }
}

TEST(RigRange, WindowsCoverEveryDisparityFromFarToNearAwayFromTheirInnerEdges) {
  for (const auto& camera : kRigs) {
    const RigRange range = rigRange(camera, {.map_resolution_m = 0.1, .precision_px = 0.1});
    ASSERT_FALSE(range.windows.empty());
    EXPECT_EQ(range.windows.front().downscale, 1);
    EXPECT_LE(range.windows.front().min_px, range.far_disparity_px);
    EXPECT_GE(range.windows.back().maxPx(), range.near_disparity_px);
    for (size_t i = 0; i < range.windows.size(); ++i) {
      const auto& w = range.windows[i];
      // A matcher's window at its own scale: whole pixels, a multiple of 16 disparities.
      EXPECT_EQ(w.min_px % w.downscale, 0);
      EXPECT_EQ(w.num_px % (16 * w.downscale), 0);
      if (i == 0) continue;
      const auto& farther = range.windows[i - 1];
      EXPECT_EQ(w.downscale, 2 * farther.downscale);
      // Each side drops its inner edge's pixel (one of its own): the overlap covers both.
      EXPECT_LE(w.min_px + w.downscale, farther.maxPx() - 1 - farther.downscale);
      // A coarser window only where its coarser disparity still puts points within a voxel:
      // dz grows with the pixel's size and falls with d^2.
      EXPECT_GE(w.min_px, range.far_disparity_px * std::sqrt(w.downscale) - 1e-9)
          << range.explain();
    }
  }
}

TEST(RigRange, TheRuleStopsWhereTheServerTakesRays) {
  // KITTI's rig with 5 m voxels: the rule says 139 m, the server refuses rays beyond 100 m.
  const RigRange range = rigRange(kRigs[1], {.map_resolution_m = 5, .precision_px = 0.1});
  EXPECT_DOUBLE_EQ(range.far_m, 70);
  EXPECT_TRUE(range.far_capped);
  EXPECT_NE(range.explain().find("capped"), std::string::npos) << range.explain();
  EXPECT_FALSE(range.windows.empty());
}

TEST(DepthStep, AnAbsurdRigIsSaidAndGivesNoPointInsteadOfACrash) {
  // A 5 km baseline (a calibration file's typo): even 70 m lies at 55,000 px of disparity,
  // beyond the image and OpenCV's int16 disparities (it crashed in the matcher).
  camera::StereoCamera absurd = kRigs[1];
  absurd.baseline = 5000;
  DepthStep depth(absurd, {});
  EXPECT_NE(depth.problem().find("beyond the image"), std::string::npos) << depth.problem();
  const cv::Mat image(absurd.height, absurd.width, CV_8UC1, cv::Scalar(100));
  EXPECT_EQ(depth.compute(image, image, std::nullopt).size(), 0u);
  for (const auto& camera : kRigs) EXPECT_EQ(DepthStep(camera, {}).problem(), "");
}

TEST(RigRange, AGivenFarLimitIsKeptAndSaidSo) {
  const RigRange range = rigRange(kRigs[1], {.map_resolution_m = 0.1, .far_m = 40});
  EXPECT_DOUBLE_EQ(range.far_m, 40);
  EXPECT_FALSE(range.far_from_rule);
  EXPECT_NE(range.explain().find("as given"), std::string::npos) << range.explain();
  EXPECT_LE(range.windows.front().min_px, kRigs[1].disparityFromDepth(40));
}

// A textured wall straight ahead at `z` metres, rendered exactly.
sim::StereoFrame wallAt(double z) {
  const sim::Scene scene({{Vec3(-20, -20, z), Vec3(20, 20, z + 0.2), 0.6f}});
  return sim::Renderer(scene, camera::StereoCamera{}).render(common::Rigid3{});
}

// Of the pixels with a disparity in [from, to): the share of all pixels, and the share of those
// within `tolerance` of `truth`.
struct Matched {
  double share = 0, right = 0;
};
Matched matched(const cv::Mat& disparity, double from, double to, double truth, double tolerance) {
  int in = 0, right = 0;
  for (int v = 0; v < disparity.rows; ++v) {
    for (int u = 0; u < disparity.cols; ++u) {
      const float d = disparity.at<float>(v, u);
      if (d < from || d >= to) continue;
      ++in;
      right += std::abs(d - truth) <= tolerance;
    }
  }
  return {in / static_cast<double>(disparity.total()), in > 0 ? right / double(in) : 1.0};
}

// Middlebury's aloe (full size, truth 43-211 px) as a rig whose far limit is its farthest
// surface (b f / 43 at 0.1 m voxels and 0.1 px), or nullopt (a failure) when it cannot be read.
std::optional<std::pair<MiddleburyPair, camera::StereoCamera>> aloeRig() {
  const auto pair = loadMiddleburyPair(testing::kDataDir / "middlebury" / "aloe");
  if (!pair.ok()) {
    ADD_FAILURE() << pair.error().message;
    return std::nullopt;
  }
  camera::StereoCamera camera = rig(pair->left.cols, pair->left.rows, pair->left.cols, 1.0);
  camera.baseline = 0.1 * 43 * 43 / 0.1 / camera.fx;
  return std::pair{*pair, camera};
}

TEST(StereoMatcher, ThePyramidFindsNearSurfacesOnRealImages) {
  // Aloe: the nearer windows, on halved and quartered images, find what lies beyond the first
  // window, and find it right.
  STEREOMAP_SKIP_WITHOUT(testing::kDataDir / "middlebury" / "aloe");
  const auto aloe = aloeRig();
  ASSERT_TRUE(aloe);
  const MiddleburyPair& pair = aloe->first;
  const camera::StereoCamera& camera = aloe->second;
  const RigRange range =
      rigRange(camera, {.map_resolution_m = 0.1, .precision_px = 0.1, .window_disparities = 48});
  ASSERT_GE(range.windows.size(), 3u) << range.explain();
  const double first_max = range.windows.front().maxPx();
  auto score = [&](const MatcherOptions& options) {
    const cv::Mat d = StereoMatcher(options).compute(pair.left, pair.right);
    // Over the evaluated pixels whose truth lies beyond the first window: found, and right.
    int beyond = 0, found = 0, right = 0;
    for (int v = 0; v < d.rows; ++v) {
      for (int u = 0; u < d.cols; ++u) {
        const float truth = pair.ground_truth.at<float>(v, u);
        if (pair.evaluated.at<uint8_t>(v, u) == 0 || truth < first_max + 2) continue;
        ++beyond;
        const float got = d.at<float>(v, u);
        if (got < 0) continue;
        ++found;
        right += std::abs(got - truth) <= 2.0f;  // the truth is whole pixels; two at half size
      }
    }
    return std::pair{found / double(beyond), right / std::max(1.0, double(found))};
  };
  const auto [one_found, one_right] =
      score(fitToRange(MatcherOptions::fast(), camera, range.far_m));
  MatcherOptions block_only = fitToWindows(MatcherOptions::fast(), range.windows);
  block_only.fill_nearer = false;
  const auto [block_found, block_right] = score(block_only);
  const auto [found, right] = score(fitToWindows(MatcherOptions::fast(), range.windows));
  EXPECT_LT(one_found * one_right, 0.05);
  // Measured: found 0.788, right 0.933; block matching alone (no semi-global fill) 0.564,
  // 0.912; one window 0.119, 0.000. The fill finds the leaves' holes and finds them right.
  EXPECT_GT(found, 0.7);
  EXPECT_GT(found, block_found + 0.15);
  EXPECT_GT(right, 0.9);
  EXPECT_GT(block_right, 0.9);
}

TEST(StereoMatcher, ThePyramidsNearerWindowsLeaveSurfacesBeyondTheRangeAlone) {
  const camera::StereoCamera camera;
  const RigRange range = rigRange(camera, {.map_resolution_m = 0.1, .precision_px = 0.1});
  const StereoMatcher pyramid(fitToWindows(MatcherOptions::fast(), range.windows));
  // A textured wall at 30 m (2 px, four times the far limit): the nearer windows' wide searches
  // find some match in its texture, unless the first window's far edge tells them off. (Their
  // semi-global fill does not run: block matching found no surface there to complete.)
  const auto frame = wallAt(30.0);
  const Matched nearer =
      matched(pyramid.compute(frame.left, frame.right), range.windows.front().maxPx(), 1e9, 0, 0);
  EXPECT_LT(nearer.share, 0.002) << 100 * nearer.share << " % of pixels came out near";
}

TEST(StereoMatcher, TheNearerWindowsFillInOnlyWhatTheImagesConfirm) {
  const camera::StereoCamera camera;
  const RigRange range = rigRange(camera, {.map_resolution_m = 0.1, .precision_px = 0.1});
  // A textured box 0.7 m ahead (84 px, in the half-size window) before the wall at 30 m: block
  // matching finds the box, so semi-global matching fills in over the whole half-size window,
  // and guesses over the wall too, where the images do not confirm it.
  const double box_z = 0.7, half_width = 0.2, half_height = 0.15;
  const sim::Scene scene(
      {{Vec3(-20, -20, 30), Vec3(20, 20, 30.2), 0.6f},
       {Vec3(-half_width, -half_height, box_z), Vec3(half_width, half_height, box_z + 0.2), 0.6f}});
  const auto frame = sim::Renderer(scene, camera).render(common::Rigid3{});
  const double box_px = camera.baseline * camera.fx / box_z;
  ASSERT_GT(box_px, range.windows.at(1).min_px + 8) << range.explain();
  ASSERT_LT(box_px, range.windows.at(1).maxPx() - 8) << range.explain();
  // The box's face in the image, and a margin of a reduced block around its edges.
  const cv::Rect face(cv::Point(cvRound(camera.cx - camera.fx * half_width / box_z),
                                cvRound(camera.cy - camera.fy * half_height / box_z)),
                      cv::Point(cvRound(camera.cx + camera.fx * half_width / box_z),
                                cvRound(camera.cy + camera.fy * half_height / box_z)));
  const int margin = 16;
  const cv::Rect inside(face.x + margin, face.y + margin, face.width - 2 * margin,
                        face.height - 2 * margin);
  const cv::Rect around(face.x - margin, face.y - margin, face.width + 2 * margin,
                        face.height + 2 * margin);
  // Of the box's face: found within a reduced pixel. Of the wall: the share matched near.
  auto score = [&](const MatcherOptions& options) {
    const cv::Mat d = StereoMatcher(options).compute(frame.left, frame.right);
    int box = 0, found = 0, wall = 0, wall_near = 0;
    for (int v = 0; v < d.rows; ++v) {
      for (int u = 0; u < d.cols; ++u) {
        const float got = d.at<float>(v, u);
        if (inside.contains({u, v})) {
          ++box;
          found += std::abs(got - box_px) <= 2.0;
        } else if (!around.contains({u, v})) {
          ++wall;
          wall_near += got >= range.windows.front().maxPx();
        }
      }
    }
    return std::pair{found / double(box), wall_near / double(wall)};
  };
  MatcherOptions block_only = fitToWindows(MatcherOptions::fast(), range.windows);
  block_only.fill_nearer = false;
  const double block_found = score(block_only).first;
  const auto [found, wall] = score(fitToWindows(MatcherOptions::fast(), range.windows));
  // Measured: the box's face found 0.449 by block matching alone, 0.733 with the fill; the wall
  // near 0.009 % (none alone), 1.58 % with the fill's guesses let through (no fit test).
  EXPECT_GT(found, block_found + 0.1);
  EXPECT_LT(wall, 0.002) << 100 * wall << " % of the wall came out near";
}

TEST(StereoMatcher, TheGroundPassFindsARoadSeenAtAGrazingAngle) {
  // A camera 0.4 m above a textured floor, looking along it: the floor's disparity rises by
  // b / h = 0.3 px a row, as KITTI's road (0.33), 4 px over a 13-row block.
  const camera::StereoCamera camera;
  const sim::Scene scene({{Vec3(-30, -30, -1), Vec3(30, 30, 0), 0.6f}});
  const common::Rigid3 T_map_camera{common::Quat(Eigen::AngleAxisd(-M_PI / 2, Vec3::UnitX())),
                                    Vec3(0, 0, 0.4)};
  const auto frame = sim::Renderer(scene, camera).render(T_map_camera);
  const RigRange range = rigRange(camera, {.map_resolution_m = 0.1, .precision_px = 0.1});
  auto score = [&](bool ground) {
    // As noisy images are matched (rows in pairs, a 13 x 26 row window): KITTI's images.
    MatcherOptions options =
        levelMatcher(fitToWindows(MatcherOptions::fast(), range.windows), DepthOptions{}.levels[0]);
    options.ground = ground;
    const StereoMatcher matcher(options);
    matcher.compute(frame.left, frame.right);  // the plane comes from the frame before
    const cv::Mat d = matcher.compute(frame.left, frame.right);
    int floor = 0, found = 0, right = 0;
    for (int v = 0; v < d.rows; ++v) {
      for (int u = 0; u < d.cols; ++u) {
        const float z = frame.depth.at<float>(v, u);
        if (z <= 0 || z > range.far_m || u < 64) continue;
        ++floor;
        if (d.at<float>(v, u) < 0) continue;
        ++found;
        right += std::abs(d.at<float>(v, u) - camera.disparityFromDepth(z)) <= 1.0;
      }
    }
    return std::pair{found / double(floor), right / std::max(1.0, double(found))};
  };
  const auto [found_without, right_without] = score(false);
  const auto [found_with, right_with] = score(true);
  std::printf("floor found %.3f right %.3f without the ground pass, %.3f %.3f with\n",
              found_without, right_without, found_with, right_with);
  // Measured: found 0.168 (right 0.465) without, 0.777 (0.980) with.
  EXPECT_GT(found_with, found_without + 0.2);
  EXPECT_GT(right_with, 0.95);
}

TEST(StereoMatcher, WindowsThatDisagreeKeepTheMatchTheImagesAgreeWith) {
  // Aloe seen by a rig whose far limit is its farthest surface (three windows): where two
  // windows match a pixel differently (a repeated texture in the wider one), the pixel takes
  // the match whose window of the images fits better instead of none.
  STEREOMAP_SKIP_WITHOUT(testing::kDataDir / "middlebury" / "aloe");
  const auto aloe = aloeRig();
  ASSERT_TRUE(aloe);
  const MiddleburyPair& pair = aloe->first;
  const camera::StereoCamera& camera = aloe->second;
  const RigRange range = rigRange(camera, {.map_resolution_m = 0.1, .precision_px = 0.1});
  const cv::Mat d = StereoMatcher(fitToWindows(MatcherOptions::fast(), range.windows))
                        .compute(pair.left, pair.right);
  int evaluated = 0, right = 0;
  for (int v = 0; v < d.rows; ++v) {
    for (int u = 0; u < d.cols; ++u) {
      const float truth = pair.ground_truth.at<float>(v, u);
      if (pair.evaluated.at<uint8_t>(v, u) == 0 || truth <= 0) continue;
      ++evaluated;
      right += std::abs(d.at<float>(v, u) - truth) <= 2.0f;
    }
  }
  // Measured: 0.810 of the pixels right; 0.758 when disagreeing windows gave none.
  EXPECT_GT(right / double(evaluated), 0.79);
}

TEST(StereoMatcher, OneWindowBehavesAsBefore) {
  // fitToWindows with one window is fitToRange's matcher: the same disparities.
  const camera::StereoCamera camera;
  const auto frame = wallAt(3.0);
  const MatcherOptions fitted = fitToRange(MatcherOptions::fast(), camera, 6.0);
  const StereoMatcher a(fitted);
  const StereoMatcher b(fitToWindows(
      MatcherOptions::fast(),
      {{.downscale = 1, .min_px = fitted.min_disparity, .num_px = fitted.num_disparities}}));
  const cv::Mat da = a.compute(frame.left, frame.right), db = b.compute(frame.left, frame.right);
  EXPECT_EQ(cv::countNonZero(da != db), 0);
}

}  // namespace
}  // namespace stereomap::stereo
