#include "onboard/posegraph/ground_test.hpp"

#include <algorithm>
#include <cmath>
#include <opencv2/calib3d.hpp>
#include <opencv2/core/eigen.hpp>

#include "onboard/camera/cv_pose.hpp"
#include "onboard/posegraph/marker_pose.hpp"

namespace stereomap::posegraph {
namespace {

using common::Quat;
using common::Rigid3;
using common::Vec3;

constexpr double kDeg = M_PI / 180.0;

// The 400 mm vehicle's markers (metres, body frame). The diagonals P1P3 and P2P4 cross, as
// the VC method needs; the layout has no symmetry, so markers are found again by it.
const Markers& vehicleMarkers() {
  static const Markers markers = {Vec3(-0.200, 0.000, 0.000), Vec3(-0.050, -0.150, 0.010),
                                  Vec3(0.200, 0.000, 0.000), Vec3(-0.050, 0.170, -0.010)};
  return markers;
}

// The body frame of eqs. 2-9 in the markers' own frame.
const Rigid3& bodyInModel() {
  static const Rigid3 body = *bodyFrameFromMarkers(vehicleMarkers());
  return body;
}

// The camera that sees the joins: 3 m in front of the volume, looking at its middle.
struct JoinCamera {
  Rigid3 T_world_camera;
  double focal_px = 1000;
};

JoinCamera joinCamera() {
  // OpenCV axes: z forward (world +y), x right (world +x), y down (world -z).
  Eigen::Matrix3d R;
  R << 1, 0, 0, 0, 0, 1, 0, -1, 0;
  return {{Quat(R), Vec3(0.3, -3.0, 0.3)}};
}

struct Truth {
  std::vector<Rigid3> T_world_body;  // the body frame of eqs. 2-9 of the true markers
  std::vector<bool> seen;
};

Truth flight(const GroundTestOptions& options, std::mt19937& rng) {
  std::normal_distribution<double> normal;
  const Vec3 direction = Vec3(normal(rng), normal(rng), normal(rng)).normalized();
  const Rigid3& body_in_model = bodyInModel();
  Truth truth;
  const int per_segment = options.frames / options.segments;
  for (int k = 0; k < options.frames; ++k) {
    const double s = std::pow(std::sin(M_PI * options.periods * k / options.frames), 2);
    const double a = options.attitude_deg * kDeg * s;
    const Quat q = Quat(Eigen::AngleAxisd(a, Vec3::UnitZ())) *
                   Quat(Eigen::AngleAxisd(a, Vec3::UnitY())) *
                   Quat(Eigen::AngleAxisd(a, Vec3::UnitX()));
    const Rigid3 T_world_model{q, direction * options.translation_mm * 1e-3 * s};
    truth.T_world_body.push_back(T_world_model * body_in_model);
    const int segment = std::min(k / per_segment, options.segments - 1);
    const bool in_gap =
        segment < options.segments - 1 && k >= (segment + 1) * per_segment - options.gap;
    truth.seen.push_back(!in_gap);
  }
  return truth;
}

Markers measure(const Rigid3& T_world_body, double sigma, std::mt19937& rng) {
  std::normal_distribution<double> noise(0.0, sigma);
  const Rigid3& body_in_model = bodyInModel();
  const Rigid3 T_world_model = T_world_body * body_in_model.inverse();
  Markers out;
  for (int m = 0; m < 4; ++m) {
    out[m] = T_world_model * vehicleMarkers()[m] + Vec3(noise(rng), noise(rng), noise(rng));
  }
  return out;
}

// The motion of the body between two frames from their markers: the earlier frame's markers,
// in its own body frame (eqs. 2-9), are the model the later frame's are fitted to.
Rigid3 relativeFromMarkers(const Markers& earlier, const Markers& later, MarkerMethod method) {
  const Rigid3 B_earlier = *bodyFrameFromMarkers(earlier);
  if (method == MarkerMethod::kBodyFrames)
    return B_earlier.inverse() * *bodyFrameFromMarkers(later);
  Markers model;
  for (int m = 0; m < 4; ++m) model[m] = B_earlier.inverse() * earlier[m];
  const auto fitted =
      method == MarkerMethod::kVectorCross
          ? vectorCrossPose(model, later)
          : leastSquaresPose({model.begin(), model.end()}, {later.begin(), later.end()});
  return fitted ? B_earlier.inverse() * *fitted : Rigid3::identity();
}

// The join over a gap: EPnP (then Levenberg-Marquardt) of the earlier frame's markers, as its
// model, in the camera's image of the later frame.
Rigid3 relativeFromImage(const Markers& earlier, const Rigid3& T_world_later_true, double sigma,
                         std::mt19937& rng) {
  const JoinCamera camera = joinCamera();
  const Rigid3 B_earlier = *bodyFrameFromMarkers(earlier);
  const double pixel_sigma = sigma * camera.focal_px / 3.0;  // the same noise, seen from 3 m
  std::normal_distribution<double> noise(0.0, pixel_sigma > 0 ? pixel_sigma : 1e-12);
  const Rigid3& body_in_model = bodyInModel();
  const Rigid3 T_camera_model =
      camera.T_world_camera.inverse() * T_world_later_true * body_in_model.inverse();
  std::vector<cv::Point3d> object;
  std::vector<cv::Point2d> image;
  for (int m = 0; m < 4; ++m) {
    const Vec3 model = B_earlier.inverse() * earlier[m];
    object.emplace_back(model.x(), model.y(), model.z());
    const Vec3 p = T_camera_model * vehicleMarkers()[m];
    image.emplace_back(camera.focal_px * p.x() / p.z() + noise(rng),
                       camera.focal_px * p.y() / p.z() + noise(rng));
  }
  const cv::Matx33d K(camera.focal_px, 0, 0, 0, camera.focal_px, 0, 0, 0, 1);
  // Four markers on a nearly flat body, 3 m away: the image fits a mirrored pose almost as
  // well. Two starts, EPnP's and the earlier frame's pose (the gap is short), each refined
  // by Levenberg-Marquardt; EPnP's wins only when it fits clearly better (by 3 sigma of the
  // pixel noise), otherwise the one nearer the earlier pose.
  auto refine = [&](cv::Mat rvec, cv::Mat tvec) {
    cv::solvePnPRefineLM(object, image, K, cv::noArray(), rvec, tvec);
    std::vector<cv::Point2d> projected;
    cv::projectPoints(object, rvec, tvec, K, cv::noArray(), projected);
    double squared = 0;
    for (size_t i = 0; i < image.size(); ++i) {
      const cv::Point2d d = projected[i] - image[i];
      squared += d.dot(d);
    }
    return std::pair{std::sqrt(squared / 4.0),
                     camera.T_world_camera * stereomap::camera::rigidFromRvecTvec(rvec, tvec)};
  };
  cv::Mat rvec, tvec;
  cv::solvePnP(object, image, K, cv::noArray(), rvec, tvec, false, cv::SOLVEPNP_EPNP);
  const auto from_epnp = refine(rvec.clone(), tvec.clone());
  const Rigid3 T_camera_earlier = camera.T_world_camera.inverse() * B_earlier;
  cv::Mat guess_r, guess_t;
  cv::eigen2cv(Eigen::Vector3d(Eigen::AngleAxisd(T_camera_earlier.rotation).axis() *
                               Eigen::AngleAxisd(T_camera_earlier.rotation).angle()),
               guess_r);
  cv::eigen2cv(Eigen::Vector3d(T_camera_earlier.translation), guess_t);
  const auto from_prior = refine(guess_r, guess_t);
  const double tie_px = 0.05 + 3.0 * pixel_sigma;
  auto distance = [&](const Rigid3& T) {
    return (B_earlier.inverse() * T).rotation.angularDistance(Quat::Identity());
  };
  const bool prior_wins = from_prior.first + tie_px < from_epnp.first ||
                          (std::abs(from_prior.first - from_epnp.first) <= tie_px &&
                           distance(from_prior.second) < distance(from_epnp.second));
  const Rigid3 T_world_later = prior_wins ? from_prior.second : from_epnp.second;
  return B_earlier.inverse() * T_world_later;
}

Vec6 logError(const Rigid3& estimate, const Rigid3& truth) {
  const Rigid3 e = truth.inverse() * estimate;
  return se3Log<double>(e.rotation, e.translation);
}

Mat6 informationOf(const std::vector<Vec6>& errors) {
  Mat6 covariance = Mat6::Zero();
  for (const auto& e : errors) covariance += e * e.transpose();
  covariance /= static_cast<double>(errors.size());
  covariance += Mat6::Identity() * 1e-14;  // noise-free runs
  return covariance.inverse();
}

}  // namespace

void GroundTestErrors::Axes::append(const Axes& other) {
  for (int a = 0; a < 3; ++a) {
    deg[a].insert(deg[a].end(), other.deg[a].begin(), other.deg[a].end());
    mm[a].insert(mm[a].end(), other.mm[a].begin(), other.mm[a].end());
  }
  deg_norm.insert(deg_norm.end(), other.deg_norm.begin(), other.deg_norm.end());
  mm_norm.insert(mm_norm.end(), other.mm_norm.begin(), other.mm_norm.end());
}

double GroundTestErrors::Axes::degPerAxis() const {
  return std::max({threeSigma(deg[0]), threeSigma(deg[1]), threeSigma(deg[2])});
}

double GroundTestErrors::Axes::mmPerAxis() const {
  return std::max({threeSigma(mm[0]), threeSigma(mm[1]), threeSigma(mm[2])});
}

double threeSigma(const std::vector<double>& values) {
  double sum = 0;
  for (const double v : values) sum += v * v;
  return values.empty() ? 0.0 : 3.0 * std::sqrt(sum / static_cast<double>(values.size()));
}

EdgeInformation calibrateEdges(const GroundTestOptions& options, std::mt19937& rng) {
  const double sigma = options.noise_mm * 1e-3 / 3.0;
  std::vector<Vec6> odometry, join;
  for (int run = 0; run < 20; ++run) {
    const Truth truth = flight(options, rng);
    for (int k = 0; k + options.frames / options.segments < options.frames; k += 2) {
      const Rigid3& a = truth.T_world_body[k];
      const Rigid3& b = truth.T_world_body[k + 1];
      odometry.push_back(logError(
          relativeFromMarkers(measure(a, sigma, rng), measure(b, sigma, rng), options.method),
          a.inverse() * b));
      const Rigid3& c = truth.T_world_body[k + options.gap + 1];
      join.push_back(
          logError(relativeFromImage(measure(a, sigma, rng), c, sigma, rng), a.inverse() * c));
    }
  }
  return {informationOf(odometry), informationOf(join)};
}

GroundTestErrors runGroundTrial(const GroundTestOptions& options,
                                const EdgeInformation& information, std::mt19937& rng) {
  const double sigma = options.noise_mm * 1e-3 / 3.0;
  const Truth truth = flight(options, rng);
  std::vector<Markers> observed(options.frames);
  std::vector<int> vertex(options.frames, -1);
  for (int k = 0; k < options.frames; ++k) {
    if (truth.seen[k]) observed[k] = measure(truth.T_world_body[k], sigma, rng);
  }

  // The linear solution (eq. 15): every seen frame chained to the one before (the markers
  // keep their names along a track; the first frame of a track joined to the last seen one
  // by EPnP), from the true first pose (the gauge). The same measurements are the graph's
  // edges.
  PoseGraph graph;
  std::vector<Rigid3> linear(options.frames);
  int previous = -1;
  for (int k = 0; k < options.frames; ++k) {
    if (!truth.seen[k]) continue;
    if (previous < 0) {
      linear[k] = truth.T_world_body[k];
      vertex[k] = graph.addVertex(linear[k]);
    } else if (k != previous + 1) {
      const Rigid3 step = relativeFromImage(observed[previous], truth.T_world_body[k], sigma, rng);
      linear[k] = linear[previous] * step;
      vertex[k] = graph.addVertex(linear[k]);
      (void)graph.addEdge({vertex[previous], vertex[k], step, information.join, EdgeKind::kJoin});
    } else {
      const Rigid3 step = relativeFromMarkers(observed[previous], observed[k], options.method);
      linear[k] = linear[previous] * step;
      vertex[k] = graph.addVertex(linear[k]);
      (void)graph.addEdge({vertex[previous], vertex[k], step, information.odometry});
    }
    previous = k;
  }

  // Loop closures: each frame registered to the nearest frame of an earlier track that the
  // linear solution puts close enough (the markers found again by their layout).
  GroundTestErrors errors;
  std::vector<int> track(options.frames, -1);
  for (int k = 0, t = -1, last = -2; k < options.frames; ++k) {
    if (!truth.seen[k]) continue;
    if (k != last + 1) ++t;
    track[k] = t;
    last = k;
  }
  for (int j = 0; j < options.frames; ++j) {
    if (!truth.seen[j]) continue;
    int best = -1;
    double best_distance = options.loop_radius_mm * 1e-3;
    for (int i = 0; i < j; ++i) {
      if (!truth.seen[i] || track[i] == track[j]) continue;
      const Rigid3 relative = linear[i].inverse() * linear[j];
      if (relative.rotation.angularDistance(Quat::Identity()) > options.loop_angle_deg * kDeg)
        continue;
      if (relative.translation.norm() < best_distance) {
        best_distance = relative.translation.norm();
        best = i;
      }
    }
    if (best < 0) continue;
    (void)graph.addEdge({vertex[best], vertex[j],
                         relativeFromMarkers(observed[best], observed[j], options.method),
                         information.odometry, EdgeKind::kLoop});
    ++errors.loop_edges;
  }
  const SolveReport report = graph.optimise();
  errors.rejected_edges = report.rejected_edges;
  errors.solve_ms = report.milliseconds;

  auto record = [](const Rigid3& estimate, const Rigid3& truth_pose, GroundTestErrors::Axes& into) {
    const Rigid3 e = truth_pose.inverse() * estimate;
    const Eigen::AngleAxisd rotation(e.rotation);
    const Vec3 attitude = rotation.axis() * rotation.angle() / kDeg;  // body axes, degrees
    const Vec3 position = (estimate.translation - truth_pose.translation) * 1e3;  // world, mm
    for (int a = 0; a < 3; ++a) {
      into.deg[a].push_back(attitude[a]);
      into.mm[a].push_back(position[a]);
    }
    into.deg_norm.push_back(attitude.norm());
    into.mm_norm.push_back(position.norm());
  };
  for (int k = 0; k < options.frames; ++k) {
    if (!truth.seen[k] || vertex[k] == 0) continue;  // the gauge is exact by construction
    record(linear[k], truth.T_world_body[k], errors.linear);
    record(graph.pose(vertex[k]), truth.T_world_body[k], errors.optimised);
  }
  return errors;
}

}  // namespace stereomap::posegraph
