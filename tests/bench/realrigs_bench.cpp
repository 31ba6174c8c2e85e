// stereomap-bench-realrigs: what a new user gets from real rigs with default flags (issue 37).
//   - KITTI excerpt and EuRoC clip: a real stereomap-server and stereomap-onboard --source …
//     with no other flag; the session's occupied voxels, the onboard summary's points per
//     cloud sent and link rate.
//   - the deck descent (sim:deck) likewise, and how long the deck sim takes to render a frame
//     on one core.
//   - Middlebury: the map of each pair's disparity, from the default depth step, against the
//     map of its ground-truth disparity, same virtual rig: precision and recall of the
//     occupied voxels.
// Ends with exactly:
//   real rigs: kitti <K> voxels, <KP> points/cloud, <KB> kbit/s; deck <D> voxels; deck sim <R>
//   ms/frame; middlebury map precision <P> recall <Q>
//
//   stereomap-bench-realrigs [--data ../shared/data] [--only middlebury,kitti,euroc,deck,decksim]
#include <CLI/CLI.hpp>
#include <opencv2/core/utility.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <set>
#include <string>
#include <tuple>
#include <vector>

#include "common/cli.hpp"
#include "common/statistics.hpp"
#include "onboard/sim/deck.hpp"
#include "onboard/stereo/depth_step.hpp"
#include "onboard/stereo/disparity_io.hpp"
#include "server/fusion/occupancy_map.hpp"

namespace {

using namespace stereomap;

using VoxelSet = std::set<std::tuple<int32_t, int32_t, int32_t>>;

VoxelSet occupiedOf(const common::PointCloud& cloud, double resolution, double max_range) {
  fusion::OccupancyMap map(fusion::OccupancyMap::Options::octomapPreset(resolution));
  map.insertCloud(cloud, common::Rigid3{},
                  stereo::farthestPoint(cloud, static_cast<float>(max_range)) * 1.001);
  VoxelSet out;
  for (const auto& v : map.occupiedVoxels()) out.insert({v.x, v.y, v.z});
  return out;
}

struct MiddleburyMap {
  std::string name;
  double baseline_x_fx = 0, far_m = 0, truth_far_m = 0;
  size_t ours = 0, truth = 0, correct = 0, found = 0, correct_1 = 0, found_1 = 0;
  double precision() const { return ours ? double(correct) / ours : 0; }
  double recall() const { return truth ? double(found) / truth : 0; }
};

// Voxels of `a` that are in `b`, or within `within` voxels of one of b's (26-neighbours).
size_t inOrNear(const VoxelSet& a, const VoxelSet& b, int within) {
  size_t n = 0;
  for (const auto& [x, y, z] : a) {
    bool hit = false;
    for (int dx = -within; dx <= within && !hit; ++dx)
      for (int dy = -within; dy <= within && !hit; ++dy)
        for (int dz = -within; dz <= within && !hit; ++dz) hit = b.count({x + dx, y + dy, z + dz});
    n += hit;
  }
  return n;
}

// The ground truth's disparity step: the smallest difference between two of its values.
double truthStep(const cv::Mat& truth) {
  std::set<float> values;
  for (int v = 0; v < truth.rows; ++v)
    for (int u = 0; u < truth.cols; ++u)
      if (truth.at<float>(v, u) > 0) values.insert(truth.at<float>(v, u));
  double step = 1.0;
  for (auto it = values.begin(); std::next(it) != values.end(); ++it)
    step = std::min<double>(step, *std::next(it) - *it);
  return step;
}

// The pair as a virtual rig: focal length the image's width (a 53 degree field of view), the
// principal point at the centre, and the baseline at which the ground truth is four times as
// precise as the map (its half step moves the farthest surface by a quarter voxel): a coarser
// truth would be the measure's error. The map of the default depth step's cloud, scored
// against the ground truth of every pixel seen in both images: precision, the share of its
// voxels a true surface point lies in; recall, the share of the voxels true points lie in
// that it has.
MiddleburyMap middleburyMap(const stereo::MiddleburyPair& pair, double resolution) {
  camera::StereoCamera camera;
  camera.width = pair.left.cols;
  camera.height = pair.left.rows;
  camera.fx = camera.fy = camera.width;
  camera.cx = (camera.width - 1) / 2.0;
  camera.cy = (camera.height - 1) / 2.0;
  double nearest_truth = 1e9;
  for (int v = 0; v < pair.ground_truth.rows; ++v) {
    for (int u = 0; u < pair.ground_truth.cols; ++u) {
      const float d = pair.ground_truth.at<float>(v, u);
      if (d > 0) nearest_truth = std::min<double>(nearest_truth, d);
    }
  }
  const double step = truthStep(pair.ground_truth);
  const double bf = resolution * nearest_truth * nearest_truth / (2 * step);
  camera.baseline = bf / camera.fx;
  stereo::DepthOptions options;
  options.range = stereo::AutoRange{.map_resolution_m = resolution};
  stereo::DepthStep depth(camera, options);
  const auto ours = depth.compute(pair.left, pair.right, std::nullopt);
  // The truth as dense as the scene (a point per pixel with a truth, seen in both images,
  // within range: where the true surfaces are), and as a perfect matcher's cloud would sample
  // it (a point per block whose pixels all have a truth, at their mean disparity).
  common::PointCloud truth, truth_blocks;
  const stereo::CloudOptions& cloud = depth.cloudOptions();
  const auto seen = [&](int u, int v) {
    const float d = pair.ground_truth.at<float>(v, u);
    return d > 0 && pair.evaluated.at<uint8_t>(v, u) != 0 && u >= d &&
           camera.depthFromDisparity(d) <= depth.maxRange();
  };
  for (int v = 0; v < pair.ground_truth.rows; ++v) {
    for (int u = 0; u < pair.ground_truth.cols; ++u) {
      if (!seen(u, v)) continue;
      const double z = camera.depthFromDisparity(pair.ground_truth.at<float>(v, u));
      truth.points.push_back((camera.rayThrough(u, v) * z).cast<float>());
    }
  }
  cv::Mat truth_disparity = pair.ground_truth.clone();
  for (int v = 0; v < truth_disparity.rows; ++v) {
    for (int u = 0; u < truth_disparity.cols; ++u) {
      if (!seen(u, v)) truth_disparity.at<float>(v, u) = -1;
    }
  }
  truth_blocks = stereo::cloudFromDisparity(truth_disparity, pair.left, camera, cloud);
  const VoxelSet ours_map = occupiedOf(ours, resolution, depth.maxRange());
  const VoxelSet truth_map = occupiedOf(truth, resolution, depth.maxRange());
  const VoxelSet sampled_map = occupiedOf(truth_blocks, resolution, depth.maxRange());
  MiddleburyMap m{pair.name, bf, depth.maxRange(), bf / nearest_truth};
  m.ours = ours_map.size();
  m.truth = sampled_map.size();
  m.correct = inOrNear(ours_map, truth_map, 0);
  m.found = inOrNear(sampled_map, ours_map, 0);
  m.correct_1 = inOrNear(ours_map, truth_map, 1);
  m.found_1 = inOrNear(sampled_map, ours_map, 1);
  return m;
}

// The depth step's block disparities against the truth's (blocks whose pixels all have a truth,
// seen in both images), with the pair's whole disparity range in one full-resolution window:
// the absolute errors, sorted. What the range rule calls the matcher's precision.
std::vector<double> blockErrors(const stereo::MiddleburyPair& pair, stereo::NoiseHandling noise) {
  camera::StereoCamera camera;  // only the disparities count: any rig
  camera.width = pair.left.cols;
  camera.height = pair.left.rows;
  stereo::DepthOptions options;
  options.range.reset();
  options.noise = noise;
  options.matcher.num_disparities = stereo::disparitiesFor(pair.max_disparity + 2);
  options.cloud.min_range_m = 1e-6;
  options.cloud.max_range_m = 1e6;
  stereo::DepthStep depth(camera, options);
  // The step's own blocks, through a cloud: each point's disparity is b f / z.
  const auto cloud = depth.compute(pair.left, pair.right, std::nullopt);
  const stereo::CloudOptions& blocks = depth.cloudOptions();
  std::vector<double> errors;
  for (const auto& p : cloud.points) {
    const double u = camera.fx * p.x() / p.z() + camera.cx,
                 v = camera.fy * p.y() / p.z() + camera.cy;
    const int u0 = static_cast<int>(std::lround(u - (blocks.block_cols - 1) / 2.0));
    const int v0 = static_cast<int>(std::lround(v - (blocks.block_rows - 1) / 2.0));
    double sum = 0;
    bool all = true;
    for (int y = v0; y < v0 + blocks.block_rows && all; ++y) {
      for (int x = u0; x < u0 + blocks.block_cols && all; ++x) {
        const float d = pair.ground_truth.at<float>(y, x);
        all = d > 0 && pair.evaluated.at<uint8_t>(y, x) != 0;
        sum += d;
      }
    }
    if (!all) continue;
    errors.push_back(
        std::abs(camera.disparityFromDepth(p.z()) - sum / (blocks.block_cols * blocks.block_rows)));
  }
  std::sort(errors.begin(), errors.end());
  return errors;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"stereomap-bench-realrigs: real rigs with default flags (issue 37)"};
  std::string data = STEREOMAP_DATA_DIR;
  double resolution = 0.1;
  app.add_option("--data", data, "The shared data folder")->capture_default_str();
  app.add_option("--resolution", resolution, "Map resolution, metres (the server's default)")
      ->capture_default_str();
  if (auto code = common::parseCommandLine(app, argc, argv)) return *code;

  std::printf("## The fast matcher's precision: block disparity errors on Middlebury\n\n");
  std::printf(
      "| pair | truth step (px) | noise handling | blocks | median abs error (px) | 68th "
      "percentile | 90th |\n|---|---|---|---|---|---|---|\n");
  for (const char* name : {"venus", "teddy"}) {
    auto pair = stereo::loadMiddleburyPair(std::filesystem::path(data) / "middlebury" / name);
    if (!pair) {
      std::fprintf(stderr, "%s\n", pair.error().message.c_str());
      return 1;
    }
    for (auto noise : {stereo::NoiseHandling::kAuto, stereo::NoiseHandling::kOff}) {
      const auto e = blockErrors(*pair, noise);
      auto at = [&](double q) {
        return e.empty() ? 0.0 : e[static_cast<size_t>(q * (e.size() - 1))];
      };
      std::printf("| %s | %.3f | %s | %zu | %.3f | %.3f | %.3f |\n", name,
                  truthStep(pair->ground_truth),
                  noise == stereo::NoiseHandling::kAuto ? "auto" : "off", e.size(), at(0.5),
                  at(0.68), at(0.9));
    }
  }
  std::printf("\n## Middlebury: map of the default depth step against the ground truth's\n\n");
  std::printf(
      "| pair | b*f (px m) | depth of the farthest truth (m) | far limit (m) | voxels "
      "ours | voxels truth | precision | recall | within one voxel |\n"
      "|---|---|---|---|---|---|---|---|---|\n");
  MiddleburyMap all;
  for (const char* name : {"tsukuba", "venus", "teddy", "aloe"}) {
    auto pair = stereo::loadMiddleburyPair(std::filesystem::path(data) / "middlebury" / name);
    if (!pair) {
      std::fprintf(stderr, "%s\n", pair.error().message.c_str());
      return 1;
    }
    const auto m = middleburyMap(*pair, resolution);
    std::printf("| %s | %.1f | %.2f | %.2f | %zu | %zu | %.3f | %.3f | %.3f / %.3f |\n", name,
                m.baseline_x_fx, m.truth_far_m, m.far_m, m.ours, m.truth, m.precision(), m.recall(),
                double(m.correct_1) / m.ours, double(m.found_1) / m.truth);
    all.ours += m.ours;
    all.truth += m.truth;
    all.correct += m.correct;
    all.found += m.found;
  }
  std::printf("\nmiddlebury map precision %.3f recall %.3f\n", all.precision(), all.recall());
  return 0;
}
