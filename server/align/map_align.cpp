#include "server/align/map_align.hpp"

#include "server/align/fpfh.hpp"
#include "server/align/icp.hpp"
#include "server/align/space_raster.hpp"

#include <omp.h>

#include <opencv2/core.hpp>
#include <opencv2/flann.hpp>

#include <open3d/geometry/KDTreeFlann.h>
#include <open3d/geometry/PointCloud.h>
#include <open3d/utility/Logging.h>

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <random>
#include <vector>

namespace stereomap::align {

namespace {

using fusion::OccupancyMap;
using open3d::geometry::KDTreeFlann;
using open3d::geometry::KDTreeSearchParamHybrid;
using open3d::geometry::PointCloud;

// OpenMP's thread count is process-wide: one alignment at a time.
std::mutex g_align_mutex;

// A map's occupied cells at every depth, as sorted Morton codes: a parent's code is its
// child's shifted by three bits, so each level comes from the finer one without sorting.
class Pyramid {
 public:
  explicit Pyramid(const OccupancyMap& map) : map_(map) {
    auto& finest = codes_[fusion::kTreeDepth];
    for (const auto& v : map.occupiedVoxels()) finest.push_back(fusion::voxelCode(v));
    std::sort(finest.begin(), finest.end());
    for (unsigned d = fusion::kTreeDepth; d > kCoarsest; --d) {
      auto& coarser = codes_[d - 1];
      for (const uint64_t code : codes_[d]) {
        if (coarser.empty() || coarser.back() != code >> 3) coarser.push_back(code >> 3);
      }
    }
  }
  static constexpr unsigned kCoarsest = 6;
  size_t size(unsigned depth) const { return codes_[depth].size(); }
  std::shared_ptr<PointCloud> cloud(unsigned depth) const {
    auto cloud = std::make_shared<PointCloud>();
    const double edge = map_.cellSize(depth);
    const int32_t offset = fusion::kKeyOffset >> (fusion::kTreeDepth - depth);
    cloud->points_.reserve(codes_[depth].size());
    for (const uint64_t code : codes_[depth]) {
      const auto key = [&](unsigned axis) {
        return static_cast<int32_t>(fusion::detail::compactBits(code >> axis)) - offset + 0.5;
      };
      cloud->points_.emplace_back(key(0) * edge, key(1) * edge, key(2) * edge);
    }
    return cloud;
  }
  const OccupancyMap& map() const { return map_; }
  const std::vector<uint64_t>& codes(unsigned depth) const { return codes_[depth]; }

 private:
  const OccupancyMap& map_;
  std::vector<uint64_t> codes_[fusion::kTreeDepth + 1];
};

// Normals point out of the surface, towards the free space the sensor saw it from: FPFH
// compares normals' directions, and a map carries no per-voxel viewpoint.
void orientTowardsFreeSpace(PointCloud& cloud, const ClassRaster& space, double edge) {
#pragma omp parallel for schedule(static)
  for (size_t i = 0; i < cloud.points_.size(); ++i) {
    const Eigen::Vector3d& p = cloud.points_[i];
    Eigen::Vector3d& n = cloud.normals_[i];
    const bool free_ahead = space.at(p + n * edge) == fusion::Occupancy::kFree;
    const bool free_behind = space.at(p - n * edge) == fusion::Occupancy::kFree;
    if (free_behind && !free_ahead) n = -n;
  }
}

// B's cells taken evenly (they are in code order: a stride spreads them over the map).
std::shared_ptr<PointCloud> thinned(std::shared_ptr<PointCloud> cloud, size_t at_most) {
  if (cloud->points_.size() <= at_most) return cloud;
  auto out = std::make_shared<PointCloud>();
  const double step = static_cast<double>(cloud->points_.size()) / at_most;
  for (size_t k = 0; k < at_most; ++k) {
    const size_t i = static_cast<size_t>(k * step);
    out->points_.push_back(cloud->points_[i]);
    if (cloud->HasNormals()) out->normals_.push_back(cloud->normals_[i]);
  }
  return out;
}

// One map at one level: its occupied cells' centres with normals, a k-d tree and a raster over
// them, the map's space classes, and an even share of the cells to count agreement with (the
// whole set is needed only as a target).
struct Side {
  const ClassRaster* space = nullptr;
  std::shared_ptr<PointCloud> cloud, sample;
  std::unique_ptr<KDTreeFlann> tree;
  std::unique_ptr<CellRaster> cells;
};

// What a side needs its normals for: features (oriented), a target of point-to-plane ICP
// and of the constraint measure (any sign), or nothing (a source only).
enum class Normals { kOriented, kUnoriented, kNone };

Side sideAt(const Pyramid& pyramid, const ClassRaster& space, unsigned depth, size_t sample,
            Normals normals) {
  Side side{&space, pyramid.cloud(depth), nullptr, nullptr, nullptr};
  const double edge = pyramid.map().cellSize(depth);
  if (normals != Normals::kNone) {
    side.cloud->EstimateNormals(KDTreeSearchParamHybrid(2.5 * edge, 30));
  }
  if (normals == Normals::kOriented) orientTowardsFreeSpace(*side.cloud, space, edge);
  side.tree = std::make_unique<KDTreeFlann>(*side.cloud);
  side.cells = std::make_unique<CellRaster>(pyramid.codes(depth), depth, edge);
  side.sample = thinned(side.cloud, sample);
  return side;
}

struct Score {
  size_t agree = 0, contradict = 0;
  double overlap = 0;  // the larger of the two maps' shares that agree
  double agreement() const {
    return agree + contradict > 0 ? static_cast<double>(agree) / (agree + contradict) : 0.0;
  }
  // A contradiction (an occupied cell where the other map saw through free space) is strong
  // evidence against a pose; an agreement is weak evidence for it (planes agree under many
  // poses). A pose that puts a room's furniture where the other flight flew counts little.
  double value() const {
    return std::max(0.0, static_cast<double>(agree) - kContradictionWeight * contradict);
  }
  static constexpr double kContradictionWeight = 10;
};

// Cells of `from` moved by T into `onto` (those `only` marks, when given): agreeing (an occupied
// cell of `onto` within 1.5 cells) or contradicting (in `onto`'s free space); the rest fall in
// unknown space.
void countInto(const Side& from, const Side& onto, const Eigen::Matrix4d& T, double edge,
               size_t& agree, size_t& contradict, const std::vector<char>* only = nullptr) {
  const Eigen::Matrix3d R = T.block<3, 3>(0, 0);
  const Eigen::Vector3d t = T.block<3, 1>(0, 3);
  const auto& points = from.sample->points_;
  size_t agreeing = 0, contradicting = 0;
#pragma omp parallel for schedule(static) reduction(+ : agreeing, contradicting)
  for (size_t i = 0; i < points.size(); ++i) {
    if (only && !(*only)[i]) continue;
    const Eigen::Vector3d q = R * points[i] + t;
    if (onto.cells->near(q, 1.5 * edge)) {
      ++agreeing;
    } else if (onto.space->at(q) == fusion::Occupancy::kFree) {
      ++contradicting;
    }
  }
  agree += agreeing;
  contradict += contradicting;
}

Score scorePose(const Side& a, const Side& b, const Eigen::Matrix4d& T_a_b, double edge) {
  size_t agree_b = 0, contra_b = 0, agree_a = 0, contra_a = 0;
  countInto(b, a, T_a_b, edge, agree_b, contra_b);
  countInto(a, b, T_a_b.inverse(), edge, agree_a, contra_a);
  Score score;
  score.agree = agree_a + agree_b;
  score.contradict = contra_a + contra_b;
  score.overlap = std::max(static_cast<double>(agree_a) / a.sample->points_.size(),
                           static_cast<double>(agree_b) / b.sample->points_.size());
  return score;
}

// Which of a side's sample cells lie off its large planes (floors, walls, facades, a road):
// a plane is large when at least 2 % of the cells (50 at the least) lie within 1.5 cells of it.
// Planes are found by position, not by the cells' normals, which stereo's noise scatters: one
// at a time, the best of planes through a cell along its normal (counted on an even share of
// the cells), fitted again to the cells it holds, and its cells taken out.
std::vector<char> offPlanes(const Side& side, double edge) {
  constexpr int kMaxPlanes = 16;
  constexpr size_t kProbes = 2000, kSeeds = 200;
  const auto& cells = side.sample->points_;
  const auto& normals = side.sample->normals_;
  const size_t n = cells.size();
  const size_t large = std::max<size_t>(50, n / 50);
  const double reach = 1.5 * edge;
  std::vector<char> off(n, 1);
  std::vector<size_t> probes;  // an even share of the cells still off every plane found
  for (size_t k = 0, step = std::max<size_t>(1, n / kProbes); k < n; k += step) probes.push_back(k);
  const auto holds = [&](const Eigen::Vector3d& normal, double offset, const Eigen::Vector3d& p) {
    return std::abs(normal.dot(p) - offset) <= reach;
  };
  for (int plane = 0; plane < kMaxPlanes && probes.size() >= 3; ++plane) {
    size_t best_count = 0;
    Eigen::Vector3d best_normal = Eigen::Vector3d::UnitZ();
    double best_offset = 0;
    for (size_t s = 0, step = std::max<size_t>(1, probes.size() / kSeeds); s < probes.size();
         s += step) {
      if (normals[probes[s]].norm() < 0.5) continue;  // a cell too isolated to have one
      const Eigen::Vector3d normal = normals[probes[s]].normalized();
      const double offset = normal.dot(cells[probes[s]]);
      size_t count = 0;
      for (const size_t i : probes) count += holds(normal, offset, cells[i]);
      if (count > best_count) best_count = count, best_normal = normal, best_offset = offset;
    }
    if (best_count < 3) break;
    // The plane fitted to the probes it holds (their centroid and least-varying direction).
    Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
    std::vector<size_t> held;
    for (const size_t i : probes) {
      if (holds(best_normal, best_offset, cells[i])) held.push_back(i), centroid += cells[i];
    }
    if (held.size() < 3) break;
    centroid /= static_cast<double>(held.size());
    Eigen::Matrix3d spread = Eigen::Matrix3d::Zero();
    for (const size_t i : held) spread += (cells[i] - centroid) * (cells[i] - centroid).transpose();
    const Eigen::Vector3d normal =
        Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(spread).eigenvectors().col(0);
    const double offset = normal.dot(centroid);
    size_t count = 0;
    for (size_t i = 0; i < n; ++i) count += off[i] && holds(normal, offset, cells[i]);
    if (count < large) break;
    for (size_t i = 0; i < n; ++i) {
      if (holds(normal, offset, cells[i])) off[i] = 0;
    }
    std::erase_if(probes, [&](size_t i) { return !off[i]; });
  }
  return off;
}

// How the matched cells' normals constrain translation (point-to-plane: each match pins its
// normal's direction only): the weakest over the strongest direction, and the weakest.
struct Constraint {
  double ratio = 0;
  Eigen::Vector3d weakest = Eigen::Vector3d::UnitX();
};

Constraint constraintOf(const Side& a, const Side& b, const Eigen::Matrix4d& T_a_b, double edge) {
  Eigen::Matrix3d sum = Eigen::Matrix3d::Zero();
  const double reach2 = (1.5 * edge) * (1.5 * edge);
  std::vector<int> index(1);
  std::vector<double> distance2(1);
  for (const auto& p : b.sample->points_) {
    const Eigen::Vector3d q = T_a_b.block<3, 3>(0, 0) * p + T_a_b.block<3, 1>(0, 3);
    if (a.tree->SearchKNN(q, 1, index, distance2) > 0 && distance2[0] <= reach2) {
      const Eigen::Vector3d& n = a.cloud->normals_[index[0]];
      sum += n * n.transpose();
    }
  }
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> solver(sum);
  const Eigen::Vector3d eigen = solver.eigenvalues();  // ascending
  Constraint out;
  out.weakest = solver.eigenvectors().col(0);
  out.ratio = eigen(2) > 0 ? std::max(0.0, eigen(0)) / eigen(2) : 0.0;
  return out;
}

// Features as rows of floats, for OpenCV's FLANN.
cv::Mat featureRows(const FpfhFeatures& feature) {
  cv::Mat rows(static_cast<int>(feature.cols()), static_cast<int>(feature.rows()), CV_32F);
  for (int i = 0; i < rows.rows; ++i) {
    for (int d = 0; d < rows.cols; ++d) rows.at<float>(i, d) = static_cast<float>(feature(d, i));
  }
  return rows;
}

// Each row's nearest row of `in` (approximate: randomized k-d trees, whose draws come from
// OpenCV's thread-local generator, seeded here so that the same maps give the same matches).
cv::Mat nearestRows(const cv::Mat& in, const cv::Mat& queries, uint32_t seed, int k) {
  cv::theRNG() = cv::RNG(seed);
  cv::flann::Index index(in, cv::flann::KDTreeIndexParams(4));
  // The queries in one part per thread: a search reads the trees only, and each query's
  // answer is its own, so the parts give the answers one search would.
  cv::Mat nearest(queries.rows, k, CV_32S);
  const int parts = omp_get_max_threads();
#pragma omp parallel for schedule(static)
  for (int part = 0; part < parts; ++part) {
    const int from = queries.rows * part / parts, to = queries.rows * (part + 1) / parts;
    if (from == to) continue;
    cv::Mat found, distances;
    index.knnSearch(queries.rowRange(from, to), found, distances, k, cv::flann::SearchParams(64));
    found.copyTo(nearest.rowRange(from, to));
  }
  return nearest;
}

constexpr int kWiderNeighbours = 3;
// A cell's feature describes at most this many of its neighbours within 5 cells.
constexpr int kFeatureNeighbours = 50;

// Each cell's nearest cells of the other map in feature space, both ways: rows of the
// kWiderNeighbours nearest, nearest first. One search serves the mutual nearest matches and
// the wider ones (a search for 3 finds the nearest at least as well as a search for 1).
struct FeatureNeighbours {
  cv::Mat b_to_a, a_to_b;
};

FeatureNeighbours featureNeighbours(const FpfhFeatures& fb, const FpfhFeatures& fa, uint32_t seed) {
  const cv::Mat rows_a = featureRows(fa), rows_b = featureRows(fb);
  return {nearestRows(rows_a, rows_b, seed, kWiderNeighbours),
          nearestRows(rows_b, rows_a, seed, kWiderNeighbours)};
}

// Mutual nearest neighbours in feature space (B's cell i, A's cell j), each among the other's
// `k` nearest; one-way nearest when too few are mutual (a repetitive scene). Exact search in
// 33 dimensions took a second for 13k cells.
// (B's cell, A's cell) pairs.
using Matches = std::vector<Eigen::Vector2i>;

Matches featureMatches(const FeatureNeighbours& nearest, int k) {
  const cv::Mat& b_to_a = nearest.b_to_a;
  const cv::Mat& a_to_b = nearest.a_to_b;
  Matches one_way, mutual;
  for (int i = 0; i < b_to_a.rows; ++i) {
    for (int n = 0; n < k; ++n) {
      const int j = b_to_a.at<int>(i, n);
      if (j < 0 || j >= a_to_b.rows) continue;
      if (n == 0) one_way.emplace_back(i, j);
      for (int m = 0; m < k; ++m) {
        if (a_to_b.at<int>(j, m) == i) {
          mutual.emplace_back(i, j);
          break;
        }
      }
    }
  }
  return mutual.size() >= 30 ? mutual : one_way;
}

double angleDeg(const Eigen::Matrix3d& R) {
  return std::acos(std::clamp((R.trace() - 1.0) / 2.0, -1.0, 1.0)) * 180.0 / M_PI;
}

struct Hypothesis {
  Eigen::Matrix4d T;
  Score score;
};

common::Rigid3 rigidOf(const Eigen::Matrix4d& T) {
  common::Rigid3 out;
  out.rotation = common::Quat(Eigen::Matrix3d(T.block<3, 3>(0, 0))).normalized();
  out.translation = T.block<3, 1>(0, 3);
  return out;
}

// A's cells within `margin` of B's (moved by T) bounding box: the rest cannot match.
std::shared_ptr<PointCloud> near(const PointCloud& a, const PointCloud& b, const Eigen::Matrix4d& T,
                                 double margin) {
  PointCloud moved = b;
  moved.Transform(T);
  const Eigen::Vector3d lo = moved.GetMinBound().array() - margin;
  const Eigen::Vector3d hi = moved.GetMaxBound().array() + margin;
  auto out = std::make_shared<PointCloud>();
  for (size_t i = 0; i < a.points_.size(); ++i) {
    const Eigen::Vector3d& p = a.points_[i];
    if ((p.array() >= lo.array()).all() && (p.array() <= hi.array()).all()) {
      out->points_.push_back(p);
      if (a.HasNormals()) out->normals_.push_back(a.normals_[i]);
    }
  }
  return out;
}

// RANSAC over feature matches (B's cell from_b[i] seen as A's to_a[i]), as Open3D's: the same
// edge-length (0.9) and distance checks, a pose counted by the matches it brings within `reach`,
// the same stop; and at the end, the matched B cells the best pose brings within `reach` of any
// A cell. But it draws three distinct matches, checks their lengths before fitting, and gives
// up on a count that can no longer win: a hundredth of Open3D's time (docs/BENCHMARKS.md).
struct RansacPose {
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  size_t matches = 0;  // within reach of their partner
  double error2 = 0;   // their squared distances, summed
  size_t landing = 0;  // matched B cells within reach of any A cell
};

RansacPose ransacOf(const std::vector<Eigen::Vector3d>& from_b,
                    const std::vector<Eigen::Vector3d>& to_a, const CellRaster& cells_a,
                    double reach, int max_draws, uint64_t seed) {
  constexpr double kConfidence = 0.999;
  constexpr double kSimilarLength = 0.9;
  const size_t n = from_b.size();
  RansacPose best;
  if (n < 3) return best;
  std::mt19937_64 random(seed);
  std::uniform_int_distribution<size_t> pick(0, n - 1);
  const double reach2 = reach * reach;
  double draws_needed = max_draws;
  for (int draw = 0; draw < max_draws && draw < draws_needed; ++draw) {
    const size_t chosen[3] = {pick(random), pick(random), pick(random)};
    if (chosen[0] == chosen[1] || chosen[1] == chosen[2] || chosen[0] == chosen[2]) continue;
    bool similar = true;
    for (const auto& [u, v] : {std::pair{0, 1}, {1, 2}, {0, 2}}) {
      const double length_b = (from_b[chosen[u]] - from_b[chosen[v]]).norm();
      const double length_a = (to_a[chosen[u]] - to_a[chosen[v]]).norm();
      if (length_b < kSimilarLength * length_a || length_a < kSimilarLength * length_b) {
        similar = false;
        break;
      }
    }
    if (!similar) continue;
    Eigen::Matrix3d source, target;
    for (int c = 0; c < 3; ++c) {
      source.col(c) = from_b[chosen[c]];
      target.col(c) = to_a[chosen[c]];
    }
    const Eigen::Matrix4d T = Eigen::umeyama(source, target, false);
    const Eigen::Matrix3d R = T.block<3, 3>(0, 0);
    const Eigen::Vector3d t = T.block<3, 1>(0, 3);
    if (((R * source).colwise() + t - target).colwise().norm().maxCoeff() > reach) continue;
    size_t matches = 0;
    double error2 = 0;
    for (size_t m = 0; m < n && matches + (n - m) >= best.matches; ++m) {
      const double d2 = (R * from_b[m] + t - to_a[m]).squaredNorm();
      if (d2 < reach2) ++matches, error2 += d2;
    }
    if (matches > best.matches ||
        (matches == best.matches && matches > 0 && error2 < best.error2)) {
      best.T = T, best.matches = matches, best.error2 = error2;
      const double all_matches = std::pow(static_cast<double>(matches) / n, 3);
      draws_needed =
          std::min(draws_needed, std::ceil(std::log(1 - kConfidence) / std::log1p(-all_matches)));
    }
  }
  if (best.matches == 0) return best;
  const Eigen::Matrix3d R = best.T.block<3, 3>(0, 0);
  const Eigen::Vector3d t = best.T.block<3, 1>(0, 3);
  for (const auto& p : from_b) best.landing += cells_a.near(R * p + t, reach);
  return best;
}

// Cells of each map counted for scores (an even share of them beyond this).
constexpr size_t kScoreSample = 40000;
// B's cells each candidate pose is refined with.
constexpr size_t kHypothesisSample = 5000;
// Space classes are cached this far around a map's occupied voxels (the octree answers beyond).
constexpr double kSpaceMargin_m = 2.0;
// How far (scoring cells) a pose is slid to see whether the match holds it.
constexpr double kSlideCells = 3;

class Progress {
 public:
  explicit Progress(const AlignOptions& options) : options_(options) {}
  void operator()(const std::string& step) const {
    if (options_.progress) options_.progress(step);
  }

 private:
  const AlignOptions& options_;
};

}  // namespace

common::Result<Alignment> alignMaps(const OccupancyMap& a, const OccupancyMap& b,
                                    const AlignOptions& options) {
  const auto start = std::chrono::steady_clock::now();
  Alignment out;
  out.voxels_a = a.occupiedCount();
  out.voxels_b = b.occupiedCount();
  if (std::abs(a.resolution() - b.resolution()) > 1e-9 * a.resolution()) {
    char text[160];
    std::snprintf(text, sizeof(text),
                  "the maps have different resolutions (%g m and %g m): align maps of one "
                  "resolution",
                  a.resolution(), b.resolution());
    return common::makeError(common::ErrorCode::kInvalidArgument, text);
  }
  for (const auto& [name, count] : {std::pair{"first", out.voxels_a}, {"second", out.voxels_b}}) {
    if (count < kMinVoxels) {
      return common::makeError(common::ErrorCode::kInvalidArgument,
                               std::string("the ") + name + " map has " + std::to_string(count) +
                                   " occupied voxels; aligning needs at least " +
                                   std::to_string(kMinVoxels));
    }
  }
  std::lock_guard lock(g_align_mutex);
  open3d::utility::SetVerbosityLevel(open3d::utility::VerbosityLevel::Error);
  omp_set_num_threads(static_cast<int>(std::max(1u, options.threads)));
  const Progress progress(options);
  // Seconds since the last lap, added to one step's account.
  auto lap_start = std::chrono::steady_clock::now();
  const auto lap = [&](double& step) {
    const auto now = std::chrono::steady_clock::now();
    step += std::chrono::duration<double>(now - lap_start).count();
    lap_start = now;
  };
  const auto finish = [&](std::string reason) {
    out.found = reason.empty();
    out.reason = std::move(reason);
    out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    return out;
  };

  // 1. Two search levels: the finest whose cells number at most max_points, and the one
  //    finer (features see structure at their own scale: a road's kerbs, a building's rooms).
  //    Poses are scored at the finer one: it shows more of what contradicts a wrong pose.
  const Pyramid pyramid_a(a), pyramid_b(b);
  unsigned depth = fusion::kTreeDepth;
  while (depth > Pyramid::kCoarsest &&
         std::max(pyramid_a.size(depth), pyramid_b.size(depth)) > options.max_points) {
    --depth;
  }
  const unsigned score_depth = std::min(depth + 1, fusion::kTreeDepth);
  const double edge = a.cellSize(depth), score_edge = a.cellSize(score_depth);
  out.working_cell_m = edge;
  const ClassRaster space_a(a, kSpaceMargin_m), space_b(b, kSpaceMargin_m);
  std::map<unsigned, Side> sides_a, sides_b;
  for (unsigned d = depth; d <= score_depth; ++d) {
    sides_a.emplace(d, sideAt(pyramid_a, space_a, d, kScoreSample, Normals::kOriented));
    sides_b.emplace(d, sideAt(pyramid_b, space_b, d, kScoreSample, Normals::kOriented));
  }
  const Side& score_a = sides_a.at(score_depth);
  const Side& score_b = sides_b.at(score_depth);
  const Eigen::Vector3d centre_b = score_b.cloud->GetCenter();
  // Poses are told apart on a share of B's cells; only the best is refined on all of them.
  const auto hypothesis_score_b = thinned(score_b.cloud, kHypothesisSample);
  const std::vector<char> off_planes_a = offPlanes(score_a, score_edge),
                          off_planes_b = offPlanes(score_b, score_edge);
  lap(out.steps.levels);

  // The best score among poses distinct from the best (sorted, best first).
  const auto rivalOf = [&](const std::vector<Hypothesis>& sorted) {
    double rival = 0;
    const Eigen::Matrix4d& top = sorted.front().T;
    for (size_t i = 1; i < sorted.size(); ++i) {
      const Eigen::Matrix4d& T = sorted[i].T;
      const double moved = ((T.block<3, 3>(0, 0) - top.block<3, 3>(0, 0)) * centre_b +
                            T.block<3, 1>(0, 3) - top.block<3, 1>(0, 3))
                               .norm();
      const double turned = angleDeg(T.block<3, 3>(0, 0).transpose() * top.block<3, 3>(0, 0));
      if (moved > options.distinct_cells * edge || turned > options.distinct_deg) {
        rival = std::max(rival, sorted[i].score.value());
      }
    }
    return rival;
  };
  // Why pose T (scoring `best_value`, its rival `second`) cannot be trusted, or "" when it
  // can; the measures go to `out`.
  const auto judge = [&](const Eigen::Matrix4d& T, double best_value, double second) {
    const Score score = scorePose(score_a, score_b, T, score_edge);
    out.overlap = score.overlap;
    out.agreement = score.agreement();
    const Constraint constraint = constraintOf(score_a, score_b, T, score_edge);
    out.constraint_ratio = constraint.ratio;
    // Slid along its weakest direction by a few cells, does the match hold as well? A road,
    // a corridor or a floor and one wall let a pose slide; a place pins it.
    double slid = 0;
    for (const double cells : {-kSlideCells, kSlideCells}) {
      Eigen::Matrix4d moved = T;
      moved.block<3, 1>(0, 3) += cells * score_edge * constraint.weakest;
      slid = std::max(slid, scorePose(score_a, score_b, moved, score_edge).value());
    }
    out.slide = score.value() > 0 ? slid / score.value() : 1.0;
    size_t off_agree = 0, off_contradict = 0;
    countInto(score_b, score_a, T, score_edge, off_agree, off_contradict, &off_planes_b);
    countInto(score_a, score_b, T.inverse(), score_edge, off_agree, off_contradict, &off_planes_a);
    out.structure_cells = off_agree + off_contradict;
    out.structure_agreement =
        off_agree + off_contradict > 0
            ? static_cast<double>(off_agree) / static_cast<double>(off_agree + off_contradict)
            : 0.0;
    char reason[256];
    if (out.overlap < options.min_overlap) {
      std::snprintf(reason, sizeof(reason),
                    "the maps do not overlap enough: %.0f%% of the smaller one matches at "
                    "best, %.0f%% needed",
                    100 * out.overlap, 100 * options.min_overlap);
    } else if (out.agreement < options.min_agreement) {
      std::snprintf(reason, sizeof(reason),
                    "no consistent match: at the best pose %.0f%% of the matched voxels fall "
                    "in the other map's free space",
                    100 * (1 - out.agreement));
    } else if (best_value <= 0 || second >= options.max_second_ratio * best_value) {
      std::snprintf(reason, sizeof(reason),
                    "ambiguous: another pose fits %.0f%% as well as the best (a symmetric or "
                    "repeated structure)",
                    best_value > 0 ? 100 * second / best_value : 100.0);
    } else if (out.constraint_ratio < options.min_constraint_ratio) {
      std::snprintf(reason, sizeof(reason),
                    "degenerate: the overlap leaves a direction of translation unconstrained "
                    "(a plain corridor or plane; constraint %.3f)",
                    out.constraint_ratio);
    } else if (out.slide >= options.max_slide) {
      std::snprintf(reason, sizeof(reason),
                    "degenerate: slid %.0f cells along its weakest direction the match holds "
                    "%.0f%% of its score (a road, a corridor, a floor and one wall)",
                    kSlideCells, 100 * out.slide);
    } else if (out.structure_cells < options.min_structure_cells) {
      std::snprintf(reason, sizeof(reason),
                    "too little to tell this place from another like it: %zu cells off the "
                    "large planes (boxes, edges, clutter) checked, %zu needed (a map of little "
                    "more than floors and walls)",
                    out.structure_cells, options.min_structure_cells);
    } else if (out.structure_agreement < options.min_structure_agreement) {
      std::snprintf(reason, sizeof(reason),
                    "another place like it: floors and walls match, but %.0f%% of what stands "
                    "off them (boxes, edges, clutter) falls in the other map's free space",
                    100 * (1 - out.structure_agreement));
    } else {
      reason[0] = '\0';
    }
    return std::string(reason);
  };

  // 2. At each search level, distinct poses: RANSAC on the matches no pose so far explains;
  //    each refined at its level and the scoring level, and scored there.
  std::vector<Hypothesis> poses;
  for (unsigned d = depth; d <= score_depth; ++d) {
    ++out.steps.levels_searched;
    const Side& side_a = sides_a.at(d);
    const Side& side_b = sides_b.at(d);
    const double cell = a.cellSize(d);
    char step[96];
    std::snprintf(step, sizeof(step), "features of %zu and %zu cells of %.2f m",
                  side_a.cloud->points_.size(), side_b.cloud->points_.size(), cell);
    progress(step);
    const auto feature_a =
        fpfhFeatures(*side_a.cloud, *side_a.tree, 5.0 * cell, kFeatureNeighbours);
    const auto feature_b =
        fpfhFeatures(*side_b.cloud, *side_b.tree, 5.0 * cell, kFeatureNeighbours);
    const FeatureNeighbours nearest = featureNeighbours(feature_b, feature_a, options.seed);
    auto remaining = featureMatches(nearest, 1);
    out.matches += remaining.size();
    progress("matching " + std::to_string(remaining.size()) + " features");
    lap(out.steps.features);
    const auto hypothesis_b = thinned(side_b.cloud, kHypothesisSample);
    // A candidate pose, refined at this level and the scoring level, and scored there.
    const auto consider = [&](const Eigen::Matrix4d& initial) {
      lap(out.steps.ransac);
      ++out.poses_tried;
      Eigen::Matrix4d T = icpPointToPlane(hypothesis_b->points_, *side_a.cloud, *side_a.tree,
                                          2.0 * cell, initial, 20, 1e-6)
                              .T_target_source;
      if (score_depth != d) {
        T = icpPointToPlane(hypothesis_score_b->points_, *score_a.cloud, *score_a.tree,
                            2.0 * score_edge, T, 20, 1e-6)
                .T_target_source;
      }
      poses.push_back({T, scorePose(score_a, score_b, T, score_edge)});
      lap(out.steps.hypotheses);
      return T;
    };
    // The best pose so far, judged; "" when it passes every gate.
    const auto verdict = [&] {
      std::vector<Hypothesis> sorted = poses;
      std::sort(sorted.begin(), sorted.end(), [](const Hypothesis& x, const Hypothesis& y) {
        return x.score.value() > y.score.value();
      });
      return sorted.empty()
                 ? std::string("no pose")
                 : judge(sorted.front().T, sorted.front().score.value(), rivalOf(sorted));
    };
    // Mutual nearest matches first; when their best pose does not pass, matches among each
    // other's 3 nearest too (more true pairs where little overlaps, more false ones too).
    std::optional<std::string> level_verdict;  // the poses' verdict, while still current
    for (const int neighbours : {1, kWiderNeighbours}) {
      if (neighbours > 1) {
        if (!options.wider_matches) break;
        level_verdict = verdict();
        lap(out.steps.judging);
        if (level_verdict->empty()) break;
        level_verdict.reset();  // more poses come: judged again below
        remaining = featureMatches(nearest, neighbours);
        out.matches += remaining.size();
        progress("matching " + std::to_string(remaining.size()) + " features, wider");
        lap(out.steps.features);
      }
      for (int k = 0; k < options.hypotheses && remaining.size() >= 3; ++k) {
        std::vector<Eigen::Vector3d> from_b, to_a;
        from_b.reserve(remaining.size());
        to_a.reserve(remaining.size());
        for (const auto& c : remaining) {
          from_b.push_back(side_b.cloud->points_[c(0)]);
          to_a.push_back(side_a.cloud->points_[c(1)]);
        }
        // Each search its own seed: what one draws does not change what another finds. The
        // first search may need many draws (little overlap); later ones look for a rival.
        const RansacPose ransac =
            ransacOf(from_b, to_a, *side_a.cells, 1.5 * cell, k == 0 ? 100000 : 30000,
                     options.seed + 1000 * d + k + (neighbours > 1 ? 500 : 0));
        if (ransac.landing < 3) break;
        const Eigen::Matrix4d refined = consider(ransac.T);
        // Matches this pose explains (before or after refinement) are not drawn from again.
        const auto explained = [&](const Eigen::Vector2i& c) {
          for (const Eigen::Matrix4d& M : {ransac.T, refined}) {
            const Eigen::Vector3d q =
                M.block<3, 3>(0, 0) * side_b.cloud->points_[c(0)] + M.block<3, 1>(0, 3);
            if ((q - side_a.cloud->points_[c(1)]).norm() < 3.0 * cell) return true;
          }
          return false;
        };
        std::erase_if(remaining, explained);
        lap(out.steps.ransac);
      }
      lap(out.steps.ransac);  // the last RANSAC, that found too few inliers
    }
    // The coarser level's best pose passes every gate: the finer search is not needed.
    if (d < score_depth && !poses.empty()) {
      out.steps.first_level_verdict = level_verdict ? *level_verdict : verdict();
      lap(out.steps.judging);
      if (out.steps.first_level_verdict.empty()) break;
    }
  }
  if (poses.empty()) return finish("no consistent feature matches between the maps");

  // The best pose, and the best of those distinct from it.
  std::sort(poses.begin(), poses.end(), [](const Hypothesis& x, const Hypothesis& y) {
    return x.score.value() > y.score.value();
  });
  const Hypothesis& best = poses.front();
  const double best_value = best.score.value();
  const double second = rivalOf(poses);
  out.confidence = best_value > 0 ? 1.0 - second / best_value : 0.0;
  // A rival that fits nearly as well refuses whatever the refinement does to the best pose
  // (the scores compared are the hypotheses'): judged as it is, without refining it.
  if (best_value <= 0 || second >= options.max_second_ratio * best_value) {
    out.T_a_b = rigidOf(best.T);
    progress("gating");
    auto reason = judge(best.T, best_value, second);
    lap(out.steps.judging);
    return finish(std::move(reason));
  }

  // 3. Level by level to the finest voxels, from the best pose.
  progress("refining");
  lap(out.steps.judging);
  Eigen::Matrix4d T = best.T;
  // Each finer level's cells of A near B's (moved), with normals, and the ICP there; at the
  // finest, the fit's error over B's sample is the RMSE reported (measured there without
  // refining when the scoring level is the finest, or a level had too little to refine with).
  double rmse = 0;
  bool refining = true;
  for (unsigned d = score_depth; d <= fusion::kTreeDepth; ++d) {
    const double cell = a.cellSize(d);
    const bool finest = d == fusion::kTreeDepth;
    const bool refine = refining && d > score_depth;
    if (!refine && !finest) continue;
    auto cells_b = thinned(pyramid_b.cloud(d), kScoreSample);
    auto cells_a = near(*pyramid_a.cloud(d), *cells_b, T, 3.0 * cell);
    if (cells_a->points_.size() < 3) {
      refining = false;
      continue;
    }
    if (refine) cells_a->EstimateNormals(KDTreeSearchParamHybrid(2.5 * cell, 30));
    const KDTreeFlann tree_a(*cells_a);
    const IcpFit fit =
        icpPointToPlane(cells_b->points_, *cells_a, tree_a, 2.0 * cell, T, refine ? 50 : 0, 1e-7);
    if (fit.matched < 3) {
      refining = false;
      continue;
    }
    T = fit.T_target_source;
    if (finest) rmse = fit.rmse;
  }
  out.T_a_b = rigidOf(T);
  out.rmse_m = rmse;
  lap(out.steps.refining);

  // 4. Gates, on the final pose at the scoring level.
  progress("gating");
  auto reason = judge(T, best_value, second);
  lap(out.steps.judging);
  return finish(std::move(reason));
}

}  // namespace stereomap::align
