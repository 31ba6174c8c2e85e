// stereomap-bench-pipeline: the time of each step of the walking skeleton's data path, on
// the simulated 640x480 camera: render a stereo pair, disparity (BM, SGBM), cloud, encode and
// decode (Draco, quantised + zstd), and one frame's OctoMap fusion at 0.1 m. Figures:
// docs/BENCHMARKS.md.
#include <benchmark/benchmark.h>
#include <opencv2/core/utility.hpp>
#include <string>

#include "onboard/sim/sim_source.hpp"
#include "onboard/stereo/depth.hpp"
#include "proto/cloud_codec.hpp"
#include "server/fusion/occupancy_map.hpp"

namespace {

using namespace stereomap;

// One rendered frame of the default flight (seed 1, t = 5 s), shared by the benchmarks.
struct Fixture {
  sim::Scene scene = sim::Scene::makeRoom({.seed = 1});
  sim::Flight flight;
  camera::StereoCamera camera;
  sim::Renderer renderer{scene, camera};
  sim::StereoFrame frame = renderer.render(flight.T_map_camera(5.0));
  cv::Mat disparity = stereo::StereoMatcher().compute(frame.left, frame.right);
  common::PointCloud cloud = stereo::cloudFromDisparity(disparity, frame.left, camera);
};

const Fixture& fixture() {
  static const Fixture instance;
  return instance;
}

// state.range(0): OpenCV threads (1 = one core).
void BM_SimRenderStereoPair(benchmark::State& state) {
  cv::setNumThreads(static_cast<int>(state.range(0)));
  const auto& f = fixture();
  for (auto _ : state) benchmark::DoNotOptimize(f.renderer.render(f.flight.T_map_camera(5.0)));
}
BENCHMARK(BM_SimRenderStereoPair)->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond);

void BM_Disparity(benchmark::State& state) {
  cv::setNumThreads(1);
  const auto& f = fixture();
  const stereo::StereoMatcher matcher(state.range(0) == 0 ? stereo::MatcherOptions::fast()
                                                          : stereo::MatcherOptions::accurate());
  state.SetLabel(state.range(0) == 0 ? "fast (BM, 48 disparities)"
                                     : "accurate (SGBM 3-way, 80 disparities)");
  for (auto _ : state) benchmark::DoNotOptimize(matcher.compute(f.frame.left, f.frame.right));
}
BENCHMARK(BM_Disparity)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond);

void BM_CloudFromDisparity(benchmark::State& state) {
  const auto& f = fixture();
  for (auto _ : state) {
    benchmark::DoNotOptimize(stereo::cloudFromDisparity(f.disparity, f.frame.left, f.camera));
  }
  state.counters["points"] = static_cast<double>(f.cloud.size());
}
BENCHMARK(BM_CloudFromDisparity)->Unit(benchmark::kMillisecond);

// state.range(0): the encoding (proto::CloudEncoding: 0 Draco, 2 quantised + zstd), 14 bits.
proto::CloudCodecOptions codecOptions(const benchmark::State& state) {
  return {.encoding = static_cast<proto::CloudEncoding>(state.range(0))};
}

void BM_CloudEncode(benchmark::State& state) {
  const auto& f = fixture();
  const auto options = codecOptions(state);
  const auto payload = proto::encodeCloud(f.cloud, options).value();
  state.SetLabel(std::string(proto::encodingName(options.encoding)));
  for (auto _ : state) benchmark::DoNotOptimize(proto::encodeCloud(f.cloud, options));
  state.counters["bytes_per_point"] =
      static_cast<double>(payload.size()) / static_cast<double>(f.cloud.size());
}
BENCHMARK(BM_CloudEncode)->Arg(0)->Arg(2)->Unit(benchmark::kMillisecond);

void BM_CloudDecode(benchmark::State& state) {
  const auto& f = fixture();
  const auto options = codecOptions(state);
  const auto payload = proto::encodeCloud(f.cloud, options).value();
  const proto::CloudPayloadInfo info{options.encoding, static_cast<uint32_t>(f.cloud.size()),
                                     f.cloud.hasIntensity()};
  state.SetLabel(std::string(proto::encodingName(options.encoding)));
  for (auto _ : state) benchmark::DoNotOptimize(proto::decodeCloud(payload, info));
}
BENCHMARK(BM_CloudDecode)->Arg(0)->Arg(2)->Unit(benchmark::kMillisecond);

// Stock OctoMap insertion (discretised) of one sim frame into an empty 0.1 m map.
void BM_FusionOneSimFrame(benchmark::State& state) {
  const auto& f = fixture();
  const auto T_map_camera = f.flight.T_map_camera(5.0);
  for (auto _ : state) {
    fusion::OccupancyMap map({.resolution = 0.1});
    map.insertCloud(f.cloud, T_map_camera, 6.0);
    benchmark::DoNotOptimize(map.occupiedCount());
  }
  state.counters["points"] = static_cast<double>(f.cloud.size());
}
BENCHMARK(BM_FusionOneSimFrame)->Unit(benchmark::kMillisecond);

}  // namespace

BENCHMARK_MAIN();
