#include "server/core/api.hpp"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "testing/synthetic.hpp"

namespace stereomap::core {
namespace {

using nlohmann::json;

TEST(Api, ListsSessionsAndServesTrajectoryAndMap) {
  MapServer server({.resolution = 0.1});
  ASSERT_TRUE(server.ingest(testing::wallFrame("flight-1", 2.05)));
  ASSERT_TRUE(server.ingest(testing::poseAt("flight-1", 0.5, 1'700'000'000'250'000'000)));
  server.find("flight-1")->waitUntilIdle();

  auto list = answerApi(server, nullptr, "GET", "/api/sessions");
  ASSERT_TRUE(list && list->status == 200);
  const auto sessions = json::parse(list->body);
  ASSERT_EQ(sessions.size(), 1u);
  EXPECT_EQ(sessions[0]["id"], "flight-1");
  EXPECT_EQ(sessions[0]["vehicle"], "v1");
  EXPECT_EQ(sessions[0]["frames"], 1);
  EXPECT_GT(sessions[0]["occupied_voxels"].get<int>(), 50);
  EXPECT_NEAR(sessions[0]["bounds"]["min"][0].get<double>(), 2.0, 1e-9);

  auto tum = answerApi(server, nullptr, "GET", "/api/sessions/flight-1/trajectory.tum");
  ASSERT_TRUE(tum && tum->status == 200);
  EXPECT_EQ(tum->body,
            "1700000000.250000000 0.500000 0.000000 0.000000 0.000000000 "
            "0.000000000 0.000000000 1.000000000\n");
  auto bt = answerApi(server, nullptr, "GET", "/api/sessions/flight-1/map.bt");
  ASSERT_TRUE(bt && bt->status == 200);
  EXPECT_EQ(bt->body.rfind("# Octomap OcTree binary file", 0), 0u);

  auto ot = answerApi(server, nullptr, "GET", "/api/sessions/flight-1/map.ot");
  ASSERT_TRUE(ot && ot->status == 200);
  EXPECT_EQ(ot->body.rfind("# Octomap OcTree file", 0), 0u);
  auto ply = answerApi(server, nullptr, "GET", "/api/sessions/flight-1/map.ply");
  ASSERT_TRUE(ply && ply->status == 200);
  const auto voxels = sessions[0]["occupied_voxels"].get<size_t>();
  const size_t header = ply->body.find("end_header\n") + 11;
  EXPECT_EQ(ply->body.size() - header, voxels * 12);  // three floats per voxel
  auto png = answerApi(server, nullptr, "GET", "/api/sessions/flight-1/map.png?zmin=-0.2&zmax=0.2");
  ASSERT_TRUE(png && png->status == 200);
  EXPECT_EQ(png->content_type, "image/png");
  EXPECT_EQ(png->body.substr(1, 3), "PNG");
  // The wall seen from above: white voxels, each a square of `scale` pixels.
  auto decoded = [](const std::string& body) {
    return cv::imdecode(std::vector<uint8_t>(body.begin(), body.end()), cv::IMREAD_UNCHANGED);
  };
  const cv::Mat one = decoded(png->body);
  ASSERT_EQ(one.type(), CV_8UC1);
  EXPECT_GT(cv::countNonZero(one), 5);
  auto png3 = answerApi(server, nullptr, "GET",
                        "/api/sessions/flight-1/map.png?zmin=-0.2&zmax=0.2&scale=3");
  ASSERT_TRUE(png3 && png3->status == 200);
  cv::Mat expected;
  cv::resize(one, expected, cv::Size(), 3, 3, cv::INTER_NEAREST);
  const cv::Mat three = decoded(png3->body);
  ASSERT_EQ(three.size(), expected.size());
  EXPECT_EQ(cv::countNonZero(three != expected), 0);
  EXPECT_EQ(
      answerApi(server, nullptr, "GET", "/api/sessions/flight-1/map.png?zmin=5&zmax=6")->status,
      404);
  EXPECT_EQ(answerApi(server, nullptr, "GET", "/api/sessions/flight-1/map.png?zmin=x")->status,
            400);
  EXPECT_EQ(answerApi(server, nullptr, "GET", "/api/sessions/flight-1/map.png?scale=40")->status,
            400);
  // The 2D grid: map_server's files; a band that is not one is the request's fault.
  auto pgm = answerApi(server, nullptr, "GET", "/api/sessions/flight-1/map2d.pgm?zmin=-1&zmax=1");
  ASSERT_TRUE(pgm && pgm->status == 200);
  EXPECT_EQ(pgm->body.rfind("P5\n", 0), 0u);
  auto yaml = answerApi(server, nullptr, "GET", "/api/sessions/flight-1/map2d.yaml?zmin=-1&zmax=1");
  ASSERT_TRUE(yaml && yaml->status == 200);
  EXPECT_NE(yaml->body.find("image: flight-1.pgm\n"), std::string::npos);
  for (const char* band : {"zmin=inf&zmax=inf", "zmin=-inf&zmax=1", "zmin=2&zmax=1"}) {
    EXPECT_EQ(
        answerApi(server, nullptr, "GET", std::string("/api/sessions/flight-1/map2d.pgm?") + band)
            ->status,
        400)
        << band;
  }
  EXPECT_EQ(
      answerApi(server, nullptr, "GET", "/api/sessions/flight-1/map2d.pgm?zmin=50&zmax=60")->status,
      404);
  EXPECT_EQ(answerApi(server, nullptr, "GET", "/api/sessions/nope/map.bt")->status, 404);
  EXPECT_EQ(answerApi(server, nullptr, "POST", "/api/sessions")->status, 405);
  EXPECT_EQ(answerApi(server, nullptr, "GET", "/api/other")->status, 404);
  EXPECT_EQ(answerApi(server, nullptr, "GET", "/healthz")->body, "ok\n");
  EXPECT_FALSE(answerApi(server, nullptr, "GET", "/index.html").has_value());
}

// A top view whose image would be gigabytes is refused before anything is allocated: two
// walls 800 m apart at 0.1 m and 16 pixels per voxel would be 128,000 pixels on a side.
TEST(Api, ATopViewTooLargeToDrawIsRefused) {
  MapServer server({.resolution = 0.1});
  ASSERT_TRUE(server.ingest(testing::wallFrame("far", 2.05, 0)));
  auto far = testing::wallFrame("far", 2.05, 1);
  far.sensor_position = {800.0, 800.0, 0.0};
  ASSERT_TRUE(server.ingest(far));
  server.find("far")->waitUntilIdle();
  const auto refused =
      answerApi(server, nullptr, "GET", "/api/sessions/far/map.png?zmin=-0.2&zmax=0.2&scale=16");
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->status, 413) << refused->body;
  EXPECT_NE(refused->body.find("smaller scale"), std::string::npos) << refused->body;
}

}  // namespace
}  // namespace stereomap::core
