// Cross-process (issue 19): stereomap-onboard descends onto the simulated moving deck with
// its landing watch on, over real DDS to a real stereomap-server; GET
// /api/sessions/{id}/landing gives what the vehicle saw, checked against the sim's truth.
// And hostile LandingTarget samples: refused with their reasons, the server unaffected.
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "onboard/landing/deck_filter.hpp"
#include "onboard/sim/deck.hpp"
#include "proto/dds.hpp"
#include "testing/synthetic.hpp"
#include "tests/support/server_fixture.hpp"
#include "tests/support/vehicle_writers.hpp"

namespace stereomap::testing {
namespace {

using namespace std::chrono_literals;
using nlohmann::json;

constexpr int kDescentDomain = 90, kHostileDomain = 92;

TEST(LandingEndToEnd, WhatTheVehicleSeesOfThePadReachesTheApi) {
  ServerProcess server(kDescentDomain);
  constexpr int kFrames = 15;
  const std::string session = "deck-descent";
  ChildProcess onboard(
      {std::string(STEREOMAP_BIN_DIR) + "/stereomap-onboard", "--source", "sim:deck", "--landing",
       "default", "--session", session, "--vehicle", "uav-1", "--frames", std::to_string(kFrames),
       "--rate", "0", "--spool", "memory", "--dds-config", STEREOMAP_DDS_CONFIG, "--domain",
       std::to_string(kDescentDomain)},
      server.logPath() + ".onboard");
  const auto code = onboard.waitExit(120s);
  ASSERT_TRUE(code.has_value() && *code == 0)
      << "onboard failed: " << server.logPath() << ".onboard";
  json landing;
  ASSERT_TRUE(waitUntil(20s,
                        [&] {
                          const auto reply = server.get("/api/sessions/" + session + "/landing");
                          if (reply.status != 200) return false;
                          landing = json::parse(reply.body);
                          return !landing["vehicles"].empty() &&
                                 landing["vehicles"][0]["seq"] == kFrames - 1;
                        }))
      << landing.dump() << "\n"
      << server.log();
  const json& seen = landing["vehicles"][0];
  EXPECT_EQ(seen["vehicle_id"], "uav-1");
  EXPECT_EQ(seen["state"], "TRACKING") << seen["reason"];
  ASSERT_TRUE(seen["has_pose"].get<bool>());

  // The truth of the last frame (10 Hz from the descent's start).
  const sim::DeckSource source({});
  const sim::DeckTruth truth = source.truthAt((kFrames - 1) / 10.0);
  EXPECT_NEAR(seen["distance_m"].get<double>(), truth.distance_m, 0.01 * truth.distance_m);
  const common::Vec3 pad_in_map(seen["pad_in_map"]["position"][0].get<double>(),
                                seen["pad_in_map"]["position"][1].get<double>(),
                                seen["pad_in_map"]["position"][2].get<double>());
  // The map is the deck's frame: the pad sits still in it, wherever the ship goes.
  const common::Vec3 pad_truth = landing::T_pad_deck().inverse().translation;
  EXPECT_LT((pad_in_map - pad_truth).norm(), 0.005 * truth.distance_m)
      << pad_in_map.transpose() << " vs " << pad_truth.transpose();
  // 1.5 s of filtering: the deck's forward speed (5 m/s) within 0.5 m/s.
  EXPECT_NEAR(seen["deck"]["velocity"][0].get<double>(), truth.deck_velocity.x(), 0.5);
  EXPECT_EQ(server.get("/api/sessions/no-such/landing").status, 404);
  EXPECT_EQ(server.process().stop(), 0);
}

TEST(LandingEndToEnd, HostileLandingTargetsAreRefusedWithTheirReasons) {
  ServerProcess server(kHostileDomain);
  auto participant = proto::Participant::create(
      {.domain_id = kHostileDomain, .config_file = STEREOMAP_DDS_CONFIG});
  ASSERT_TRUE(participant.ok()) << participant.error().message;
  VehicleWriters<proto::CloudFrameMsg> clouds(*participant);
  VehicleWriters<proto::LandingTargetMsg> targets(*participant);
  const std::string session = "hostile-landing";
  ASSERT_TRUE(clouds.write(planeFrame("tester", session, 0, planeCloud(2.0, 1.0, 0.02))).ok());
  ASSERT_TRUE(waitUntil(20s, [&] { return server.get("/api/sessions/" + session).status == 200; }));

  auto target = [&](const std::string& vehicle, const std::string& in_session) {
    proto::LandingTargetMsg t;
    t.vehicle_id = vehicle;
    t.session_id = in_session;
    t.seq = 1;
    t.stamp_ns = 10;
    t.state = proto::LandingState::kTracking;
    t.reason = "followed";
    t.has_pose = true;
    t.camera_position = {0, 0, 20};
    t.map_position = {1, 2, 0};
    t.distance = 20;
    return t;
  };
  auto nowhere = target("a", "no-such-session");
  auto bad_id = target("../etc", session);
  auto nan = target("b", session);
  nan.map_position[1] = std::nan("");
  auto quaternion = target("c", session);
  quaternion.camera_orientation = {0, 0, 0, 2};
  auto control = target("d", session);
  control.reason = "line\nbreak";
  auto bytes = target("f", session);  // not UTF-8: JSON could not carry it
  bytes.reason = "caf\xe9 \xff";
  auto negative = target("e", session);
  negative.map_covariance[0] = -1;
  auto good = target("good", session);
  // A volatile topic: a sample written before the server matched its writer would be lost;
  // VehicleWriters waits for the server's reader.
  for (const auto* t : {&nowhere, &bad_id, &nan, &quaternion, &control, &bytes, &negative, &good}) {
    ASSERT_TRUE(targets.write(*t).ok());
  }
  auto rejected = [](const std::string& metrics, const std::string& reason) {
    return seriesValue(
        metrics,
        "stereomap_samples_rejected_total{topic=\"LandingTarget\",reason=\"" + reason + "\"}");
  };
  std::string metrics;
  EXPECT_TRUE(waitUntil(
      20s,
      [&] {
        metrics = server.get("/metrics").body;
        return rejected(metrics, "unknown_session") == 1 && rejected(metrics, "bad_id") == 1 &&
               rejected(metrics, "non_finite") == 2 && rejected(metrics, "bad_quaternion") == 1 &&
               rejected(metrics, "bad_text") == 2 &&
               seriesValue(metrics, "stereomap_samples_accepted_total{topic=\"LandingTarget\"}") ==
                   1;
      }))
      << metrics << "\n"
      << server.log();
  const json landing = json::parse(server.get("/api/sessions/" + session + "/landing").body);
  ASSERT_EQ(landing["vehicles"].size(), 1u) << landing.dump();
  EXPECT_EQ(landing["vehicles"][0]["vehicle_id"], "good");
  EXPECT_EQ(server.get("/healthz").status, 200);
  EXPECT_EQ(server.process().stop(), 0);
}

}  // namespace
}  // namespace stereomap::testing
