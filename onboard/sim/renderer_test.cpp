#include "onboard/sim/renderer.hpp"

#include <gtest/gtest.h>

#include <cmath>

#include <opencv2/imgproc.hpp>

#include "onboard/sim/deck.hpp"
#include "onboard/sim/flight.hpp"

namespace stereomap::sim {
namespace {

using common::Rigid3;
using common::Vec3;

// A wall facing the camera (OpenCV frame: z forward) at depth `z`, much wider than the view.
Scene wallAt(double z) { return Scene({{Vec3(-100, -100, z), Vec3(100, 100, z + 1)}}); }

TEST(Renderer, DepthOfAFrontoParallelPlaneIsExact) {
  const Scene scene = wallAt(3.0);
  const Renderer renderer(scene, camera::StereoCamera{});
  const StereoFrame frame = renderer.render(Rigid3::identity());
  ASSERT_EQ(frame.depth.size(), cv::Size(640, 480));
  double lo, hi;
  cv::minMaxLoc(frame.depth, &lo, &hi);
  EXPECT_EQ(lo, 3.0);
  EXPECT_EQ(hi, 3.0);
}

TEST(Renderer, DepthOfATiltedPlaneMatchesTheRayIntersection) {
  // Floor 1.5 m below a camera looking along the horizon: depth = 1.5 * fy / (v - cy).
  const Scene scene({{Vec3(-50, 1.5, -50), Vec3(50, 2.5, 50)}});
  const camera::StereoCamera camera;
  const Renderer renderer(scene, camera);
  const cv::Mat depth = renderer.renderDepth(Rigid3::identity());
  for (int v : {300, 400, 479}) {  // nearer than max_depth
    const double expected = 1.5 * camera.fy / (v - camera.cy);
    EXPECT_NEAR(depth.at<float>(v, 100), expected, 1e-5 * expected) << "row " << v;
  }
  EXPECT_EQ(depth.at<float>(100, 100), 0.0f);  // above the horizon: no surface
}

TEST(Renderer, RightImageIsTheLeftShiftedByTheTrueDisparity) {
  const camera::StereoCamera camera;
  const int disparity = 20;
  const Scene scene = wallAt(camera.depthFromDisparity(disparity));
  const Renderer renderer(scene, camera);
  const StereoFrame frame = renderer.render(Rigid3::identity());
  int worst = 0;
  for (int v = 0; v < camera.height; v += 7) {
    for (int u = disparity; u < camera.width; u += 3) {
      worst = std::max(worst, std::abs(frame.left.at<uint8_t>(v, u) -
                                       frame.right.at<uint8_t>(v, u - disparity)));
    }
  }
  EXPECT_LE(worst, 1);
  // The texture has contrast for the matcher to use.
  cv::Scalar mean, stddev;
  cv::meanStdDev(frame.left, mean, stddev);
  EXPECT_GT(stddev[0], 15.0);
}

TEST(Renderer, IsDeterministicForASeed) {
  const Scene a = Scene::makeRoom({.seed = 4});
  const Scene b = Scene::makeRoom({.seed = 4});
  const Scene c = Scene::makeRoom({.seed = 5});
  const Flight flight;
  const Renderer ra(a, {}), rb(b, {}), rc(c, {});
  const auto pose = flight.T_map_camera(3.0);
  EXPECT_EQ(cv::norm(ra.render(pose).left, rb.render(pose).left, cv::NORM_INF), 0.0);
  EXPECT_GT(cv::norm(ra.render(pose).left, rc.render(pose).left, cv::NORM_L1), 0.0);
}

// The camera model, one effect at a time, against the exact images of the same view.
StereoFrame renderWith(const Scene& scene, const CameraModel& model,
                       const std::optional<Renderer::Exposure>& exposure = std::nullopt) {
  return Renderer(scene, camera::StereoCamera{}, {.camera = model})
      .render(Rigid3::identity(), exposure);
}

TEST(CameraModel, PresetsByNameAndCleanIsExact) {
  const Scene scene = wallAt(3.0);
  ASSERT_TRUE(CameraModel::preset("clean"));
  ASSERT_TRUE(CameraModel::preset("typical"));
  ASSERT_TRUE(CameraModel::preset("poor"));
  EXPECT_FALSE(CameraModel::preset("Typical"));
  EXPECT_EQ(CameraModel::preset("poor")->right_gain, 1.10);
  const auto exact = renderWith(scene, {});
  const auto clean = renderWith(scene, *CameraModel::preset("clean"));
  EXPECT_EQ(cv::norm(exact.left, clean.left, cv::NORM_INF), 0.0);
  EXPECT_EQ(cv::norm(exact.right, clean.right, cv::NORM_INF), 0.0);
  const auto typical = renderWith(scene, CameraModel::typical());
  EXPECT_GT(cv::norm(exact.left, typical.left, cv::NORM_L1), 0.0);
}

TEST(CameraModel, TheRightCamerasGainScalesItsImageAndOnlyIts) {
  const Scene scene = wallAt(3.0);
  const auto exact = renderWith(scene, {});
  const auto brighter = renderWith(scene, {.right_gain = 1.10});
  EXPECT_EQ(cv::norm(exact.left, brighter.left, cv::NORM_INF), 0.0);
  EXPECT_NEAR(cv::sum(brighter.right)[0] / cv::sum(exact.right)[0], 1.10, 0.01);
}

TEST(CameraModel, VignettingDarkensTheCornersByItsFraction) {
  const Scene scene = wallAt(3.0);
  const auto exact = renderWith(scene, {});
  const auto vignetted = renderWith(scene, {.vignetting = 0.3});
  auto ratio = [&](const cv::Rect& box) {
    return cv::sum(vignetted.left(box))[0] / cv::sum(exact.left(box))[0];
  };
  EXPECT_NEAR(ratio(cv::Rect(310, 230, 20, 20)), 1.0, 0.01);  // at the principal point
  EXPECT_NEAR(ratio(cv::Rect(0, 0, 6, 6)), 0.7, 0.02);        // the farthest corner
  EXPECT_NEAR(ratio(cv::Rect(634, 474, 6, 6)), 0.7, 0.03);
}

TEST(CameraModel, ShotNoiseGrowsWithTheLevelAndReadNoiseDoesNot) {
  // The wall's texture spans dark and bright levels: noise measured on each.
  const Scene scene = wallAt(3.0);
  const auto exact = renderWith(scene, {});
  const auto noisy = renderWith(scene, {.noise_sigma = 2.0, .shot_noise = 0.05});
  cv::Mat exact_f, noisy_f;
  exact.left.convertTo(exact_f, CV_64F);
  noisy.left.convertTo(noisy_f, CV_64F);
  const cv::Mat difference = noisy_f - exact_f;
  // Variance against the expected 4 + 0.05 * level, level by level (the texture spans many).
  double dark_sum = 0, dark_expected = 0, bright_sum = 0, bright_expected = 0;
  int dark_n = 0, bright_n = 0;
  for (int v = 0; v < difference.rows; ++v) {
    for (int u = 0; u < difference.cols; ++u) {
      const double level = exact_f.at<double>(v, u), d = difference.at<double>(v, u);
      if (level < 20 || level > 235) continue;  // clipped at 0 or 255
      if (level < 100) {
        dark_sum += d * d, dark_expected += 4 + 0.05 * level, ++dark_n;
      } else if (level > 150) {
        bright_sum += d * d, bright_expected += 4 + 0.05 * level, ++bright_n;
      }
    }
  }
  ASSERT_GT(dark_n, 1000);
  ASSERT_GT(bright_n, 1000);
  // Measured variance within 10 % of the model's (+1/12 for rounding to whole grey levels).
  EXPECT_NEAR(dark_sum / dark_n, dark_expected / dark_n + 1.0 / 12, 0.1 * dark_expected / dark_n);
  EXPECT_NEAR(bright_sum / bright_n, bright_expected / bright_n + 1.0 / 12,
              0.1 * bright_expected / bright_n);
  EXPECT_GT(bright_sum / bright_n, dark_sum / dark_n + 2.0);
}

TEST(CameraModel, MotionBlurSmearsAlongTheImageMotionOnly) {
  // The camera turns about its y axis while the shutter is open: the image moves sideways
  // by f * angle (6 px here): the image is smeared along that line and no other way.
  const Scene scene = wallAt(3.0);
  const camera::StereoCamera camera;
  const double angle = 6.0 / camera.fx;
  const Renderer::Exposure turning{
      {common::Quat(Eigen::AngleAxisd(-angle / 2, Vec3::UnitY())), Vec3::Zero()},
      {common::Quat(Eigen::AngleAxisd(angle / 2, Vec3::UnitY())), Vec3::Zero()}};
  const auto sharp = renderWith(scene, {.exposure_s = 0.01});  // no poses: no blur
  const auto blurred = renderWith(scene, {.exposure_s = 0.01}, turning);
  const auto still = renderWith(scene, {}, turning);  // no exposure time: no blur
  EXPECT_EQ(cv::norm(sharp.left, still.left, cv::NORM_INF), 0.0);
  // The same as smearing the sharp image along a horizontal line of 6 px.
  const cv::Mat line = (cv::Mat_<float>(1, 7) << 0.5f, 1, 1, 1, 1, 1, 0.5f) / 6.0f;
  cv::Mat smeared;
  cv::filter2D(sharp.left, smeared, -1, line, cv::Point(-1, -1), 0, cv::BORDER_REFLECT);
  const cv::Rect inner(10, 10, 620, 460);
  const double from_sharp = cv::norm(blurred.left(inner), sharp.left(inner), cv::NORM_L1);
  const double from_smeared = cv::norm(blurred.left(inner), smeared(inner), cv::NORM_L1);
  EXPECT_GT(from_sharp, 0.0);
  EXPECT_LT(from_smeared, 0.2 * from_sharp);  // measured 0.05
}

TEST(CameraModel, GammaIsTheResponseCurve) {
  const Scene scene = wallAt(3.0);
  const auto exact = renderWith(scene, {});
  const auto curved = renderWith(scene, {.gamma = 1.25});
  for (int v = 0; v < 480; v += 37) {
    for (int u = 0; u < 640; u += 41) {
      const double in = exact.left.at<uint8_t>(v, u);
      EXPECT_NEAR(curved.left.at<uint8_t>(v, u), 255.0 * std::pow(in / 255.0, 1 / 1.25), 0.5);
    }
  }
}

// A deck (the sim's, with its pad) with boxes standing on it, one painted on top: the
// anti-aliased path must find every box's and marking's edges, not only the deck's. Its own
// boxes, so that the figures below do not move with the sim's scene.
Scene deckWithCrates() {
  Scene scene({{Vec3(-20, -8, -1), Vec3(20, 8, 0), 0.6f},         // the deck
               {Vec3(-300, -300, -6), Vec3(300, 300, -5), 0.3f},  // the sea
               {Vec3(2.2, 0.4, 0), Vec3(3.4, 1.6, 0.8), 0.35f},   // crates
               {Vec3(-5, -3, 0), Vec3(-3.5, -1.8, 1.5), 0.8f}},
              1);
  const SceneMarking pad = makeDeckScene(1).markings().front();
  EXPECT_EQ(pad.box, 0);
  scene.addMarking(pad);
  scene.addMarking(
      {.box = 2, .polygon = {{2.4, 0.6}, {3.2, 0.6}, {3.2, 1.4}, {2.4, 1.4}}, .albedo = 0.9f});
  return scene;
}

// Looking straight down from `height` above (x, y) of the deck, turned 20 deg so that no edge
// runs along the pixel grid.
Rigid3 lookingDown(double x, double y, double height) {
  return {
      common::Quat(Eigen::AngleAxisd(0.35, Vec3::UnitZ()) * Eigen::AngleAxisd(M_PI, Vec3::UnitX())),
      Vec3(x, y, height)};
}

// The left image, clean camera; `supersample` above 1 takes the anti-aliased path.
cv::Mat renderLeft(const Scene& scene, const camera::StereoCamera& camera, const Rigid3& pose,
                   int supersample) {
  return Renderer(scene, camera, {.max_depth = 80, .supersample = supersample}).render(pose).left;
}

// Brute force: one ray per pixel of an image `s` times larger, averaged down (each pixel the
// mean of s x s rays over it, the texture unfiltered).
cv::Mat bruteForceLeft(const Scene& scene, const camera::StereoCamera& camera, const Rigid3& pose,
                       int s) {
  camera::StereoCamera fine = camera;
  fine.width *= s, fine.height *= s, fine.fx *= s, fine.fy *= s;
  fine.cx = s * camera.cx + (s - 1) / 2.0;
  fine.cy = s * camera.cy + (s - 1) / 2.0;
  cv::Mat reference;
  cv::resize(renderLeft(scene, fine, pose, 1), reference, cv::Size(camera.width, camera.height), 0,
             0, cv::INTER_AREA);
  return reference;
}

// Against brute force at 8 x 8 rays a pixel (measured figures in comments). On the pixels that
// an edge crosses (where one ray a pixel is more than 20 grey levels off: boxes' outlines, the
// pad's and the crate's paint): with only each pixel's right and lower neighbours compared,
// 16 % and 31 % of them stayed that far off (mean errors 11.0 and 12.7). Over the whole image
// after a blur of 1.5 px (detail finer than the pixels is what the fast path fades and brute
// force aliases). And the detail finer than that blur: kept up close, less of it far away (the
// 6 cm octave at a 6 cm footprint).
TEST(Renderer, AntiAliasedDeckAgreesWithBruteForceSupersampling) {
  const Scene scene = deckWithCrates();
  // A quarter of the image, to keep brute force quick; the lens as the deck's.
  const camera::StereoCamera camera{.width = 320, .height = 240, .cx = 159.5, .cy = 119.5};
  struct View {
    double height;
    Rigid3 pose;
    double edge_error, edge_share_off, blurred_error, blurred_worst, detail_ratio_min,
        detail_ratio_max;
  };
  for (const View& view : {
           View{30, lookingDown(-0.5, 0, 30), 10.0 /* 6.8 */, 0.06 /* 0.026 */, 4.0 /* 2.7 */,
                20 /* 15.2 */, 0.4, 0.8 /* 0.58 */},
           View{3, lookingDown(1.9, 1.0, 3), 5.0 /* 3.0 */, 0.02 /* 0 */, 1.0 /* 0.56 */,
                10 /* 6.1 */, 0.95, 1.05 /* 1.00 */},
       }) {
    SCOPED_TRACE(testing::Message() << view.height << " m");
    cv::Mat fast, one_ray, reference;
    renderLeft(scene, camera, view.pose, 3).convertTo(fast, CV_32F);
    renderLeft(scene, camera, view.pose, 1).convertTo(one_ray, CV_32F);
    bruteForceLeft(scene, camera, view.pose, 8).convertTo(reference, CV_32F);

    const cv::Mat edges = cv::abs(one_ray - reference) > 20;
    const int edge_pixels = cv::countNonZero(edges);
    ASSERT_GT(edge_pixels, 200);                                        // 269 and 254
    EXPECT_GT(cv::mean(cv::abs(one_ray - reference), edges)[0], 25.0);  // 33.5, 33.7
    EXPECT_LT(cv::mean(cv::abs(fast - reference), edges)[0], view.edge_error);
    // An edge missed leaves its pixel as one ray saw it: the share still that far off.
    const cv::Mat off = edges & (cv::abs(fast - reference) > 20);
    EXPECT_LT(cv::countNonZero(off) / static_cast<double>(edge_pixels), view.edge_share_off);

    cv::Mat fast_blurred, reference_blurred;
    cv::GaussianBlur(fast, fast_blurred, cv::Size(), 1.5);
    cv::GaussianBlur(reference, reference_blurred, cv::Size(), 1.5);
    const cv::Mat blurred_error = cv::abs(fast_blurred - reference_blurred);
    double worst;
    cv::minMaxLoc(blurred_error, nullptr, &worst);
    EXPECT_LT(cv::mean(blurred_error)[0], view.blurred_error);
    EXPECT_LT(worst, view.blurred_worst);

    auto detail = [](const cv::Mat& image, const cv::Mat& blurred) {
      cv::Scalar mean, stddev;
      cv::meanStdDev(image - blurred, mean, stddev);
      return stddev[0];
    };
    const double ratio = detail(fast, fast_blurred) / detail(reference, reference_blurred);
    EXPECT_GT(ratio, view.detail_ratio_min);
    EXPECT_LT(ratio, view.detail_ratio_max);
  }
}

// The first pass in four lanes of floats (the default) against the reference in doubles, over
// the deck descent (clean camera, so only the rendering differs): the same images but for a
// float's rounding. Measured: 0.012 % of pixels differ, none by more than 1 grey level but at a
// box's edge (one pixel in 3 million by 9: one of its 9 rays on the other side).
TEST(Renderer, LanesAgreeWithTheReferenceInDoubles) {
  int64_t pixels = 0, differ = 0, far_off = 0;
  for (const double t : {0.0, 20.0, 40.0, 58.0}) {
    cv::Mat image[2];
    for (const bool lanes : {true, false}) {
      DeckSourceOptions options{.max_frames = 1, .start_s = t};
      options.render.camera = CameraModel::clean();
      options.render.lanes = lanes;
      DeckSource source(options);
      image[lanes ? 0 : 1] = source.next()->left;
    }
    cv::Mat difference;
    cv::absdiff(image[0], image[1], difference);
    pixels += difference.total();
    differ += cv::countNonZero(difference > 0);
    far_off += cv::countNonZero(difference > 1);
  }
  EXPECT_LT(differ, pixels / 2000);  // 0.05 %
  EXPECT_LE(far_off, 4);
}

TEST(Flight, StaysInsideTheRoomAndClearOfObstacles) {
  for (uint32_t seed : {1u, 2u, 3u}) {
    const Scene room = Scene::makeRoom({.seed = seed});
    EXPECT_GE(room.boxes().size(), 10u) << "seed " << seed;  // 5 walls/floor + obstacles
    const Flight flight;
    for (double t = 0; t < flight.options().period_s; t += 0.25) {
      const Vec3 p = flight.T_map_body(t).translation;
      EXPECT_GT(room.distanceToSurface(p), 0.5) << "seed " << seed << " t " << t;
      EXPECT_TRUE(room.bounds().contains(p));
    }
  }
}

TEST(Flight, CameraLooksForwardAndSlightlyDown) {
  const Flight flight;
  const auto T_map_body = flight.T_map_body(0);
  const Vec3 optical_axis = flight.T_map_camera(0).rotation * Vec3::UnitZ();
  const Vec3 body_forward = T_map_body.rotation * Vec3::UnitX();
  EXPECT_GT(optical_axis.dot(body_forward), 0.95);
  EXPECT_LT(optical_axis.z(), 0.0);
}

}  // namespace
}  // namespace stereomap::sim
