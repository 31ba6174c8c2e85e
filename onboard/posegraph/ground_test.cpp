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

// The pose of the body in the world from one frame's markers, against the track's model of
// the markers (body coordinates).
std::optional<Rigid3> fitModel(const Markers& model, const Markers& world, MarkerMethod method) {
  if (method == MarkerMethod::kBodyFrames) return bodyFrameFromMarkers(world);
  return method == MarkerMethod::kVectorCross
             ? vectorCrossPose(model, world)
             : leastSquaresPose({model.begin(), model.end()}, {world.begin(), world.end()});
}

// The markers in the body frame of eqs. 2-9, from every frame of a track (or only its first,
// `frames` of 1): each frame is fitted to the model, brought back into the body frame, and
// the model is their mean, three times over (generalised Procrustes).
Markers trackModel(const std::vector<const Markers*>& frames, MarkerMethod method) {
  auto inBodyFrame = [](const Markers& markers) {
    const Rigid3 B = *bodyFrameFromMarkers(markers);
    Markers model;
    for (int m = 0; m < 4; ++m) model[m] = B.inverse() * markers[m];
    return model;
  };
  Markers model = inBodyFrame(*frames.front());
  for (int round = 0; round < (frames.size() > 1 ? 3 : 0); ++round) {
    Markers mean;
    mean.fill(Vec3::Zero());
    for (const Markers* frame : frames) {
      const Rigid3 P = fitModel(model, *frame, method).value_or(Rigid3::identity()).inverse();
      for (int m = 0; m < 4; ++m) mean[m] += P * (*frame)[m] / static_cast<double>(frames.size());
    }
    model = inBodyFrame(mean);
  }
  return model;
}

// The join over a gap: EPnP (then Levenberg-Marquardt) of the earlier track's model in the
// camera's image of the later frame, as a motion from the earlier frame's pose B_earlier.
Rigid3 relativeFromImage(const Markers& model, const Rigid3& B_earlier,
                         const Rigid3& T_world_later_true, double sigma, std::mt19937& rng) {
  const JoinCamera camera = joinCamera();
  const double pixel_sigma = sigma * camera.focal_px / 3.0;  // the same noise, seen from 3 m
  std::normal_distribution<double> noise(0.0, pixel_sigma > 0 ? pixel_sigma : 1e-12);
  const Rigid3& body_in_model = bodyInModel();
  const Rigid3 T_camera_model =
      camera.T_world_camera.inverse() * T_world_later_true * body_in_model.inverse();
  std::vector<cv::Point3d> object;
  std::vector<cv::Point2d> image;
  for (int m = 0; m < 4; ++m) {
    object.emplace_back(model[m].x(), model[m].y(), model[m].z());
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

void appendError(const Rigid3& estimate, const Rigid3& truth, GroundTestErrors::Axes& into) {
  const Rigid3 e = truth.inverse() * estimate;
  const Eigen::AngleAxisd rotation(e.rotation);
  const Vec3 attitude = rotation.axis() * rotation.angle() / kDeg;         // body axes, degrees
  const Vec3 position = (estimate.translation - truth.translation) * 1e3;  // world, mm
  for (int a = 0; a < 3; ++a) {
    into.deg[a].push_back(attitude[a]);
    into.mm[a].push_back(position[a]);
  }
  into.deg_norm.push_back(attitude.norm());
  into.mm_norm.push_back(position.norm());
}

// The rigid transform G of the world that best brings a trial's estimates onto the truth
// (G * estimate ~ truth): attitude by the mean of the rotations, then position.
Rigid3 alignment(const std::vector<Rigid3>& estimate, const std::vector<Rigid3>& truth) {
  Eigen::Vector4d sum = Eigen::Vector4d::Zero();
  for (size_t k = 0; k < estimate.size(); ++k) {
    Quat q = truth[k].rotation * estimate[k].rotation.conjugate();
    if (q.w() < 0) q.coeffs() *= -1;
    sum += q.coeffs();
  }
  Rigid3 G;
  if (estimate.empty()) return G;
  G.rotation = Quat(sum.normalized());
  Vec3 offset = Vec3::Zero();
  for (size_t k = 0; k < estimate.size(); ++k)
    offset += truth[k].translation - G.rotation * estimate[k].translation;
  G.translation = offset / static_cast<double>(estimate.size());
  return G;
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
  const int per_track = options.frames / options.segments;
  std::vector<Vec6> odometry, join;
  for (int run = 0; run < 20; ++run) {
    const Truth truth = flight(options, rng);
    std::vector<Markers> observed;
    std::vector<const Markers*> frames;
    for (int k = 0; k < per_track; ++k)
      observed.push_back(measure(truth.T_world_body[k], sigma, rng));
    for (const auto& o : observed) frames.push_back(&o);
    if (!options.track_model) frames.resize(1);
    const Markers model = trackModel(frames, options.method);
    std::vector<Rigid3> P;
    for (const auto& o : observed)
      P.push_back(fitModel(model, o, options.method).value_or(Rigid3::identity()));
    for (int k = 0; k + 1 < per_track; ++k) {
      const Rigid3& a = truth.T_world_body[k];
      const Rigid3& b = truth.T_world_body[k + 1];
      odometry.push_back(logError(P[k].inverse() * P[k + 1], a.inverse() * b));
      const Rigid3& c = truth.T_world_body[k + options.gap + 1];
      join.push_back(logError(relativeFromImage(model, P[k], c, sigma, rng), a.inverse() * c));
    }
  }
  return {informationOf(odometry), informationOf(join)};
}

GroundTestErrors::Axes oneFrameErrors(const GroundTestOptions& options, std::mt19937& rng) {
  const double sigma = options.noise_mm * 1e-3 / 3.0;
  const Truth truth = flight(options, rng);
  Markers model;  // the true layout, in the body frame of eqs. 2-9
  for (int m = 0; m < 4; ++m) model[m] = bodyInModel().inverse() * vehicleMarkers()[m];
  GroundTestErrors::Axes errors;
  for (const Rigid3& pose : truth.T_world_body) {
    const auto fitted = fitModel(model, measure(pose, sigma, rng), MarkerMethod::kLeastSquares);
    appendError(fitted.value_or(Rigid3::identity()), pose, errors);
  }
  return errors;
}

GroundTestErrors runGroundTrial(const GroundTestOptions& options,
                                const EdgeInformation& information, std::mt19937& rng) {
  const double sigma = options.noise_mm * 1e-3 / 3.0;
  const Truth truth = flight(options, rng);
  std::vector<Markers> observed(options.frames);
  for (int k = 0; k < options.frames; ++k) {
    if (truth.seen[k]) observed[k] = measure(truth.T_world_body[k], sigma, rng);
  }
  // Tracks: runs of seen frames (the markers keep their names along one).
  std::vector<int> track(options.frames, -1), first_of_track;
  for (int k = 0, last = -2; k < options.frames; ++k) {
    if (!truth.seen[k]) continue;
    if (k != last + 1) first_of_track.push_back(k);
    track[k] = static_cast<int>(first_of_track.size()) - 1;
    last = k;
  }
  std::vector<Markers> models;
  for (size_t t = 0; t < first_of_track.size(); ++t) {
    std::vector<const Markers*> frames;
    for (int k = first_of_track[t]; k < options.frames && track[k] == static_cast<int>(t); ++k)
      frames.push_back(&observed[k]);
    if (!options.track_model) frames.resize(1);
    models.push_back(trackModel(frames, options.method));
  }
  std::vector<Rigid3> P(options.frames);  // each frame's pose in the world by its track's model
  for (int k = 0; k < options.frames; ++k) {
    if (truth.seen[k])
      P[k] = fitModel(models[track[k]], observed[k], options.method).value_or(Rigid3::identity());
  }

  // The linear solution (eq. 15): every frame of a track placed by its pose relative to the
  // track's first frame, the first frame of a track joined to the last seen one by EPnP, from
  // the true first pose (the gauge). The same measurements are the graph's edges.
  PoseGraph graph;
  std::vector<Rigid3> linear(options.frames);
  std::vector<int> vertex(options.frames, -1);
  int previous = -1;
  for (int k = 0; k < options.frames; ++k) {
    if (!truth.seen[k]) continue;
    const int first = first_of_track[track[k]];
    if (previous < 0) {
      linear[k] = truth.T_world_body[k];
      vertex[k] = graph.addVertex(linear[k]);
    } else if (k == first) {
      const Rigid3 step = relativeFromImage(models[track[previous]], P[previous],
                                            truth.T_world_body[k], sigma, rng);
      linear[k] = linear[previous] * step;
      vertex[k] = graph.addVertex(linear[k]);
      (void)graph.addEdge({vertex[previous], vertex[k], step, information.join, EdgeKind::kJoin});
    } else {
      linear[k] = linear[first] * P[first].inverse() * P[k];
      vertex[k] = graph.addVertex(linear[k]);
      (void)graph.addEdge(
          {vertex[previous], vertex[k], P[previous].inverse() * P[k], information.odometry});
    }
    previous = k;
  }

  // Loop closures: each frame registered to the nearest frame of an earlier track that the
  // linear solution puts close enough (the markers found again by their layout).
  GroundTestErrors errors;
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
    (void)graph.addEdge(
        {vertex[best], vertex[j], P[best].inverse() * P[j], information.odometry, EdgeKind::kLoop});
    ++errors.loop_edges;
  }
  const SolveReport report = graph.optimise();
  errors.rejected_edges = report.rejected_edges;
  errors.solve_ms = report.milliseconds;

  auto record = [&](const std::vector<Rigid3>& all, GroundTestErrors::Axes& into) {
    std::vector<Rigid3> estimate, truth_poses;
    for (int k = 0; k < options.frames; ++k) {
      // Unaligned, the gauge is exact by construction; aligned, it is a pose like the others.
      if (!truth.seen[k] || (!options.align && vertex[k] == 0)) continue;
      estimate.push_back(all[k]);
      truth_poses.push_back(truth.T_world_body[k]);
    }
    const Rigid3 G = options.align ? alignment(estimate, truth_poses) : Rigid3::identity();
    for (size_t k = 0; k < estimate.size(); ++k) appendError(G * estimate[k], truth_poses[k], into);
  };
  std::vector<Rigid3> optimised(options.frames);
  for (int k = 0; k < options.frames; ++k)
    if (vertex[k] >= 0) optimised[k] = graph.pose(vertex[k]);
  record(linear, errors.linear);
  record(optimised, errors.optimised);
  return errors;
}

}  // namespace stereomap::posegraph
