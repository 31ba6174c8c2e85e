// The window's bundle adjustment: converges to the true scene from a perturbed start, agrees
// with Ceres (automatic derivatives, same robust cost) on a noisy problem, and recovers a
// right-image offset that the data implies.
#include "onboard/odometry/detail/bundle.hpp"

#include <ceres/ceres.h>
#include <gtest/gtest.h>

#include <random>

#include "onboard/odometry/detail/reprojection.hpp"
#include "onboard/odometry/detail/rotation.hpp"

namespace stereomap::odometry::detail {
namespace {

camera::StereoCamera testCamera() {
  camera::StereoCamera c;
  c.width = 640;
  c.height = 480;
  c.fx = c.fy = 450;
  c.cx = 320;
  c.cy = 240;
  c.baseline = 0.12;
  return c;
}

// Five poses moving forward and turning, 150 points 3-30 m ahead, every point seen in both
// cameras of every frame (with `offset` added to the right columns) plus pixel noise.
BundleProblem scene(double noise_px, double offset, uint32_t seed) {
  const auto cam = testCamera();
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> unit(-1, 1);
  std::normal_distribution<double> noise(0, noise_px);
  BundleProblem p;
  for (int f = 0; f < 5; ++f) {
    const common::Rigid3 T_world_camera{
        common::Quat(Eigen::AngleAxisd(0.03 * f, Eigen::Vector3d::UnitY())),
        common::Vec3(0.05 * f, 0.02 * f, 0.4 * f)};
    p.T_camera_world.push_back(T_world_camera.inverse());
  }
  for (int j = 0; j < 150; ++j) {
    const double z = 3 + 27 * (0.5 + 0.5 * unit(rng));
    p.points.emplace_back(unit(rng) * 0.5 * z, unit(rng) * 0.4 * z, z);
  }
  for (int f = 0; f < 5; ++f) {
    for (int j = 0; j < 150; ++j) {
      const common::Vec3 c =
          p.T_camera_world[static_cast<size_t>(f)] * p.points[static_cast<size_t>(j)];
      const double u = cam.fx * c.x() / c.z() + cam.cx, v = cam.fy * c.y() / c.z() + cam.cy;
      const double ur = cam.fx * (c.x() - cam.baseline) / c.z() + cam.cx + offset;
      p.observations.push_back({f, j, u + noise(rng), v + noise(rng), false});
      p.observations.push_back({f, j, ur + noise(rng), v + noise(rng), true});
    }
  }
  return p;
}

void perturb(BundleProblem& p, uint32_t seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> n(0, 1);
  for (size_t f = 1; f < p.T_camera_world.size(); ++f) {
    p.T_camera_world[f].rotation =
        common::Quat(
            Eigen::AngleAxisd(0.01, Eigen::Vector3d(n(rng), n(rng), n(rng)).normalized())) *
        p.T_camera_world[f].rotation;
    p.T_camera_world[f].translation += 0.05 * common::Vec3(n(rng), n(rng), n(rng));
  }
  for (auto& x : p.points) x += 0.02 * x.z() * common::Vec3(n(rng), n(rng), n(rng));
}

double poseError(const BundleProblem& a, const BundleProblem& b) {
  double worst = 0;
  for (size_t f = 0; f < a.T_camera_world.size(); ++f) {
    const common::Rigid3 d = a.T_camera_world[f].inverse() * b.T_camera_world[f];
    worst = std::max(worst,
                     d.translation.norm() + d.rotation.angularDistance(common::Quat::Identity()));
  }
  return worst;
}

TEST(Bundle, ConvergesToTheTruthWithoutNoise) {
  const BundleProblem truth = scene(0.0, 0.0, 1);
  BundleProblem p = truth;
  perturb(p, 2);
  ASSERT_GT(poseError(p, truth), 0.01);
  const auto summary = adjustBundle(testCamera(), p, {.iterations = 20, .huber_px = 1.0});
  EXPECT_LT(summary.final_cost, 1e-12 * summary.initial_cost + 1e-12);
  EXPECT_LT(poseError(p, truth), 1e-6);
}

// The same cost written for Ceres with automatic derivatives.
struct CeresResidual {
  CeresResidual(const camera::StereoCamera& c, const BundleObservation& o)
      : r(c, o.u, o.v, o.right ? c.baseline : 0.0), right(o.right) {}
  template <typename T>
  bool operator()(const T* aa, const T* t, const T* point, const T* offset, T* out) const {
    r(aa, t, point, out);
    if (right) out[0] += offset[0];
    return true;
  }
  PinholeResidual r;
  bool right;
};

struct CeresOffsetPrior {
  template <typename T>
  bool operator()(const T* offset, T* out) const {
    out[0] = (offset[0] - T(start)) / T(sigma);
    return true;
  }
  double start, sigma;
};

TEST(Bundle, AgreesWithCeresOnANoisyProblem) {
  const auto cam = testCamera();
  BundleProblem p = scene(0.7, 0.4, 3);
  perturb(p, 4);
  p.right_offset_sigma = 0.5;
  BundleProblem q = p;
  const auto summary = adjustBundle(cam, p, {.iterations = 50, .huber_px = 1.0});
  EXPECT_LT(summary.offset_sigma_px, 0.5);  // determined by this window: refined

  std::vector<Eigen::Vector3d> aa, t;
  for (const auto& T : q.T_camera_world) {
    aa.push_back(angleAxisOf(T.rotation));
    t.push_back(T.translation);
  }
  double offset = q.right_offset;
  ceres::Problem::Options problem_options;
  problem_options.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  ceres::Problem problem(problem_options);
  ceres::HuberLoss huber(1.0);
  for (const auto& o : q.observations) {
    const auto f = static_cast<size_t>(o.frame);
    problem.AddResidualBlock(
        new ceres::AutoDiffCostFunction<CeresResidual, 2, 3, 3, 3, 1>(new CeresResidual(cam, o)),
        &huber, aa[f].data(), t[f].data(), q.points[static_cast<size_t>(o.point)].data(), &offset);
  }
  problem.AddResidualBlock(new ceres::AutoDiffCostFunction<CeresOffsetPrior, 1, 1>(
                               new CeresOffsetPrior{q.right_offset, q.right_offset_sigma}),
                           nullptr, &offset);
  problem.SetParameterBlockConstant(aa[0].data());
  problem.SetParameterBlockConstant(t[0].data());
  ceres::Solver::Options solver;
  solver.linear_solver_type = ceres::DENSE_SCHUR;
  solver.max_num_iterations = 100;
  solver.function_tolerance = solver.gradient_tolerance = solver.parameter_tolerance = 1e-14;
  ceres::Solver::Summary ceres_summary;
  ceres::Solve(solver, &problem, &ceres_summary);
  for (size_t f = 0; f < aa.size(); ++f) q.T_camera_world[f] = {quatOf(aa[f]), t[f]};

  EXPECT_LT(poseError(p, q), 1e-5);
  EXPECT_NEAR(p.right_offset, offset, 1e-4);
  EXPECT_NEAR(p.right_offset, 0.4, 0.1);  // the offset in the data
}

TEST(Bundle, HeldOffsetStaysPut) {
  BundleProblem p = scene(0.3, 0.0, 5);
  perturb(p, 6);
  p.right_offset = 0.25;  // right_offset_sigma = 0: not estimated
  const auto summary = adjustBundle(testCamera(), p, {.iterations = 20});
  EXPECT_EQ(p.right_offset, 0.25);
  EXPECT_LT(summary.final_cost, 0.5 * summary.initial_cost);  // the rest is still adjusted
}

TEST(Bundle, AWindowThatCannotTellTheOffsetHoldsIt) {
  // Five identical poses (a vehicle standing still): depth and offset trade freely.
  BundleProblem p = scene(0.3, 0.0, 7);
  for (auto& T : p.T_camera_world) T = p.T_camera_world.front();
  const auto cam = testCamera();
  for (auto& o : p.observations) {  // re-observe from the one pose
    const common::Vec3 c = p.T_camera_world[0] * p.points[static_cast<size_t>(o.point)];
    o.u =
        cam.fx * (c.x() - (o.right ? cam.baseline : 0.0)) / c.z() + cam.cx + (o.right ? 0.6 : 0.0);
    o.v = cam.fy * c.y() / c.z() + cam.cy;
  }
  p.right_offset_sigma = 0.5;
  const auto summary = adjustBundle(cam, p, {.iterations = 20});
  EXPECT_GT(summary.offset_sigma_px, 10.0);
  EXPECT_NEAR(p.right_offset, 0.0, 1e-6);
}

}  // namespace
}  // namespace stereomap::odometry::detail
