// stereomap-bench-realrigs: what a new user gets from real rigs with default flags (issue 37).
//   - KITTI excerpt and EuRoC clip: a real stereomap-server and stereomap-onboard --source …
//     with no other flag; the session's occupied voxels, the onboard summary's points per
//     cloud sent and link rate.
//   - the deck descent (sim:deck) likewise, with the landing watch and every frame taken
//     (--skip-late off): its frames late, and how long the deck sim takes to render a frame
//     on one core.
//   - Middlebury: the map of each pair's disparity, from the default depth step, against the
//     map of its ground-truth disparity, same virtual rig: precision and recall of the
//     occupied voxels.
// Ends with exactly:
//   real rigs: kitti <K> voxels, <KP> points/cloud, <KB> kbit/s; deck <D> voxels; deck sim <R>
//   ms/frame; middlebury map precision <P> recall <Q>; landing descent <LF> late of <LN>
// (the deck descent flown at 10 Hz with every frame taken: LF of its LN frames late)
//
//   stereomap-bench-realrigs [--data ../shared/data] [--only middlebury,kitti,euroc,deck,decksim]
#include <CLI/CLI.hpp>
#include <opencv2/core/utility.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <set>
#include <string>
#include <tuple>
#include <vector>

#include <nlohmann/json.hpp>

#include <regex>

#include "common/cli.hpp"
#include "common/statistics.hpp"
#include "onboard/sim/deck.hpp"
#include "onboard/stereo/depth_step.hpp"
#include "onboard/stereo/disparity_io.hpp"
#include "server/fusion/occupancy_map.hpp"
#include "tests/support/map_score.hpp"
#include "tests/support/server_fixture.hpp"

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
  MiddleburyMap m{pair.name, bf, depth.range()->far_m, bf / nearest_truth};
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

// One flight as a new user makes it: a real stereomap-server and stereomap-onboard --source
// SOURCE with no other flag but where DDS runs (`extra`: for comparisons). What the server
// holds once it has fused everything, and what the vehicle's summary says it sent.
struct Flight {
  bool ok = false;
  size_t voxels = 0;
  double points_per_cloud = 0, kbit_s = 0;
  uint64_t clouds_sent = 0, clouds_offered = 0, clouds_empty = 0;
  // The vehicle's frames: how many, how many late (begun a period or more after their slot),
  // the slowest, and the furthest behind its slot one began.
  uint64_t frames = 0, late = 0;
  double slowest_ms = 0, behind_ms = 0;
  std::string depth_range, map_bt, log;
};

Flight fly(const std::string& source, int domain, const std::vector<std::string>& extra = {}) {
  using namespace std::chrono_literals;
  Flight flight;
  testing::ServerProcess server(domain);
  const std::string session = "realrigs";
  std::vector<std::string> argv = {std::string(STEREOMAP_BIN_DIR) + "/stereomap-onboard",
                                   "--source",
                                   source,
                                   "--session",
                                   session,
                                   "--dds-config",
                                   STEREOMAP_DDS_CONFIG,
                                   "--domain",
                                   std::to_string(domain),
                                   "--spool",
                                   "memory"};
  argv.insert(argv.end(), extra.begin(), extra.end());
  const std::string log_path = server.logPath() + ".onboard";
  testing::ChildProcess onboard(argv, log_path);
  const auto code = onboard.waitExit(600s);
  {
    std::ifstream in(log_path);
    flight.log.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  }
  if (!code || *code != 0) {
    std::fprintf(stderr, "%s: the vehicle failed (%s)\n%s\n", source.c_str(), log_path.c_str(),
                 flight.log.c_str());
    return flight;
  }
  std::smatch m;
  if (std::regex_search(flight.log, m, std::regex(R"(link: sent (\d+) kbit/s)"))) {
    flight.kbit_s = std::stod(m[1]);
  }
  if (std::regex_search(
          flight.log, m,
          std::regex(R"((\d+) of (\d+) clouds \((\d+) skipped with nothing new, (\d+) empty)"))) {
    flight.clouds_sent = std::stoull(m[1]);
    flight.clouds_offered = std::stoull(m[2]);
    flight.clouds_empty = std::stoull(m[4]);
  }
  if (std::regex_search(flight.log, m,
                        std::regex(R"(([\d.]+) points and [\d.]+ KiB per cloud sent)"))) {
    flight.points_per_cloud = std::stod(m[1]);
  }
  if (std::regex_search(
          flight.log, m,
          std::regex(R"(done: (\d+) frames.*slowest ([\d.]+) ms, at most ([\d.]+) ms )"
                     R"(behind, (\d+) late,)"))) {
    flight.frames = std::stoull(m[1]);
    flight.slowest_ms = std::stod(m[2]);
    flight.behind_ms = std::stod(m[3]);
    flight.late = std::stoull(m[4]);
  }
  if (std::regex_search(flight.log, m, std::regex(R"(depth range: ([^\n]*))"))) {
    flight.depth_range = m[1];
  }
  // Fused: the session ended, nothing waiting.
  nlohmann::json status;
  const bool fused = testing::waitUntil(120s, [&] {
    const auto reply = server.get("/api/sessions/" + session);
    if (reply.status != 200) return false;
    status = nlohmann::json::parse(reply.body, nullptr, false);
    return status.is_object() && status.value("state", "") == "ended" &&
           status.value("fusion_backlog", 1) == 0 && status.value("deferred_frames", 1) == 0 &&
           status.value("frames", uint64_t{0}) == status.value("frames_received", uint64_t{1});
  });
  if (!fused) {
    std::fprintf(stderr, "%s: the server did not fuse the session: %s\n", source.c_str(),
                 status.dump().c_str());
    return flight;
  }
  flight.voxels = status.value("occupied_voxels", size_t{0});
  flight.map_bt = server.get("/api/sessions/" + session + "/map.bt").body;
  flight.ok = true;
  return flight;
}

// The deck map's voxels against the deck scene (the map is the deck's frame): the share a
// true surface passes through, and within one voxel of one.
std::pair<double, double> deckPrecision(const Flight& flight, double resolution) {
  const auto occupied = testing::occupiedVoxelsOf(flight.map_bt, resolution);
  if (!occupied || occupied->empty()) return {0, 0};
  const sim::Scene scene = sim::makeDeckScene(1);
  const double half_diagonal = resolution * std::sqrt(3.0) / 2;
  size_t in = 0, near = 0;
  for (const auto& [x, y, z] : *occupied) {
    const double d = scene.distanceToSurface(
        common::Vec3((x + 0.5) * resolution, (y + 0.5) * resolution, (z + 0.5) * resolution));
    in += d <= half_diagonal;
    near += d <= half_diagonal + resolution;
  }
  return {in / double(occupied->size()), near / double(occupied->size())};
}

// Milliseconds per frame of the deck sim (DeckSource::next(): both images, the camera model)
// on one core, over `frames` frames spread over the descent: the median, and the slowest.
std::pair<double, double> deckSimMs(int frames) {
  cv::setNumThreads(1);
  std::vector<double> ms;
  for (int i = 0; i < frames; ++i) {
    sim::DeckSourceOptions options{.max_frames = 1, .start_s = 60.0 * i / frames};
    sim::DeckSource source(options);
    const auto start = std::chrono::steady_clock::now();
    const auto frame = source.next();
    ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
                     .count());
    if (!frame) break;
  }
  cv::setNumThreads(-1);
  const double slowest = *std::max_element(ms.begin(), ms.end());
  return {common::median(std::move(ms)).value_or(0.0), slowest};
}

// The fast matcher's block disparity errors on the pairs with sub-pixel truth, by noise
// handling; returns the default way's median (both pairs), or nullopt when the data is absent.
std::optional<double> reportPrecision(const std::string& data) {
  std::printf("## The fast matcher's precision: block disparity errors on Middlebury\n\n");
  std::printf(
      "| pair | truth step (px) | noise handling | blocks | median abs error (px) | 68th "
      "percentile | 90th |\n|---|---|---|---|---|---|---|\n");
  std::vector<double> pooled;  // the default way (noise handling auto), both pairs
  for (const char* name : {"venus", "teddy"}) {
    auto pair = stereo::loadMiddleburyPair(std::filesystem::path(data) / "middlebury" / name);
    if (!pair) {
      std::fprintf(stderr, "%s\n", pair.error().message.c_str());
      return std::nullopt;
    }
    for (auto noise : {stereo::NoiseHandling::kAuto, stereo::NoiseHandling::kOff}) {
      const auto e = blockErrors(*pair, noise);
      if (noise == stereo::NoiseHandling::kAuto) pooled.insert(pooled.end(), e.begin(), e.end());
      auto at = [&](double q) {
        return e.empty() ? 0.0 : e[static_cast<size_t>(q * (e.size() - 1))];
      };
      std::printf("| %s | %.3f | %s | %zu | %.3f | %.3f | %.3f |\n", name,
                  truthStep(pair->ground_truth),
                  noise == stereo::NoiseHandling::kAuto ? "auto" : "off", e.size(), at(0.5),
                  at(0.68), at(0.9));
    }
  }
  const double median = common::median(pooled).value_or(0.0);
  std::printf(
      "\nfast matcher's precision (median absolute block error, both pairs, noise handling "
      "auto): %.3f px (MatcherOptions::precision_px is %.3f)\n\n",
      median, stereo::MatcherOptions::fast().precision_px);
  return median;
}

// The map of each pair against its truth's; the sums over the pairs, or nullopt.
std::optional<MiddleburyMap> reportMiddlebury(const std::string& data, double resolution) {
  std::printf("## Middlebury: map of the default depth step against the ground truth's\n\n");
  std::printf(
      "| pair | b*f (px m) | depth of the farthest truth (m) | far limit (m) | voxels "
      "ours | voxels truth | precision | recall | within one voxel |\n"
      "|---|---|---|---|---|---|---|---|---|\n");
  MiddleburyMap all;
  for (const char* name : {"tsukuba", "venus", "teddy", "aloe"}) {
    auto pair = stereo::loadMiddleburyPair(std::filesystem::path(data) / "middlebury" / name);
    if (!pair) {
      std::fprintf(stderr, "%s\n", pair.error().message.c_str());
      return std::nullopt;
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
  std::printf("\nmiddlebury map precision %.3f recall %.3f\n\n", all.precision(), all.recall());
  return all;
}

void reportFlight(const char* name, const Flight& f) {
  std::printf("| %s | %zu | %.0f | %.0f | %llu / %llu (%llu) | %s |\n", name, f.voxels,
              f.points_per_cloud, f.kbit_s, static_cast<unsigned long long>(f.clouds_sent),
              static_cast<unsigned long long>(f.clouds_offered),
              static_cast<unsigned long long>(f.clouds_empty), f.depth_range.c_str());
  std::fflush(stdout);
}

void reportDeckPrecision(const char* what, const Flight& f, double resolution) {
  const auto [in, near] = deckPrecision(f, resolution);
  std::printf("%s: precision %.3f (a surface in the voxel), %.3f (within one voxel)\n", what, in,
              near);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"stereomap-bench-realrigs: real rigs with default flags (issue 37)"};
  std::string data = STEREOMAP_DATA_DIR;
  double resolution = 0.1;
  std::vector<std::string> only = {"middlebury", "kitti", "euroc", "deck", "decksim"};
  bool physics = false;
  app.add_option("--data", data, "The shared data folder")->capture_default_str();
  app.add_option("--resolution", resolution, "Map resolution, metres (the server's default)")
      ->capture_default_str();
  app.add_option("--only", only, "Parts to run (the last line needs them all)")
      ->delimiter(',')
      ->check(CLI::IsMember({"middlebury", "kitti", "euroc", "deck", "decksim"}))
      ->capture_default_str();
  app.add_flag("--deck-from-30", physics,
               "Also fly the deck with --max-range 30: what mapping beyond the rig's precision "
               "gives");
  if (auto code = common::parseCommandLine(app, argc, argv)) return *code;
  const auto wanted = [&](const char* part) {
    return std::find(only.begin(), only.end(), part) != only.end();
  };

  std::optional<MiddleburyMap> middlebury;
  if (wanted("middlebury")) {
    if (!reportPrecision(data)) return 1;
    middlebury = reportMiddlebury(data, resolution);
    if (!middlebury) return 1;
  }
  std::printf("## Real sources, default flags: stereomap-server + stereomap-onboard --source\n\n");
  std::printf(
      "| source | occupied voxels | points per cloud sent | kbit/s | clouds sent / made "
      "(empty) | depth range |\n|---|---|---|---|---|---|\n");
  Flight kitti, euroc, deck;
  if (wanted("kitti")) {
    kitti = fly("kitti:" + data + "/kitti_stereo_seq2", 101);
    reportFlight("KITTI excerpt (51 frames)", kitti);
  }
  if (wanted("euroc")) {
    euroc = fly("euroc:" + data + "/euroc_v101_micro", 102);
    reportFlight("EuRoC clip (40 frames)", euroc);
  }
  if (wanted("deck")) {
    // Every frame taken (--skip-late off), so that a frame the watch made late shows.
    deck = fly("sim:deck", 103, {"--landing", "default", "--skip-late", "off"});
    reportFlight("deck descent (600 frames, landing watch on)", deck);
    std::printf(
        "\nlanding descent at 10 Hz, every frame taken: %llu of %llu frames late, the slowest "
        "%.1f ms, at most %.0f ms behind its slot\n",
        static_cast<unsigned long long>(deck.late), static_cast<unsigned long long>(deck.frames),
        deck.slowest_ms, deck.behind_ms);
    if (physics) {
      const Flight from30 = fly("sim:deck", 104, {"--landing", "default", "--max-range", "30"});
      reportFlight("deck descent, --max-range 30 (beyond the rig's precision)", from30);
      reportDeckPrecision("\nthe deck map with --max-range 30 against the deck scene", from30,
                          resolution);
    }
    reportDeckPrecision("the deck map against the deck scene", deck, resolution);
  }
  double sim_ms = 0;
  if (wanted("decksim")) {
    double slowest = 0;
    std::tie(sim_ms, slowest) = deckSimMs(60);
    std::printf(
        "\ndeck sim: %.1f ms per frame on one core (median of 60 over the descent; slowest "
        "%.1f)\n",
        sim_ms, slowest);
  }
  if (only.size() < 5) return 0;
  std::printf(
      "\nreal rigs: kitti %zu voxels, %.0f points/cloud, %.0f kbit/s; deck %zu voxels; deck "
      "sim %.1f ms/frame; middlebury map precision %.3f recall %.3f; landing descent %llu late "
      "of %llu\n",
      kitti.voxels, kitti.points_per_cloud, kitti.kbit_s, deck.voxels, sim_ms,
      middlebury->precision(), middlebury->recall(), static_cast<unsigned long long>(deck.late),
      static_cast<unsigned long long>(deck.frames));
  return kitti.ok && euroc.ok && deck.ok ? 0 : 1;
}
