// Cross-process: a real stereomap-server receives bad samples over real DDS (a truncated
// Draco payload, a NaN pose, an oversize cloud, a non-unit quaternion) between good ones.
// It must stay up, count each rejection with its reason, and keep fusing the good samples.
// And hostile viewers on /ws (protocol 2): malformed JSON, unknown types, huge, unmasked and
// binary frames, bad tokens, missing sessions: a clear error, the connection closed where it
// must be, the server unaffected.
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <filesystem>
#include <fstream>

#include "proto/cloud_codec.hpp"
#include "proto/dds.hpp"
#include "testing/synthetic.hpp"
#include "tests/support/server_fixture.hpp"
#include "tests/support/vehicle_writers.hpp"
#include "tests/support/websocket_client.hpp"

namespace stereomap::testing {
namespace {

using namespace std::chrono_literals;

constexpr int kDomain = 72;
const std::string kSession = "bad-input";

proto::CloudFrameMsg wallFrame(uint64_t seq, double x) {
  return planeFrame("tester", kSession, seq, planeCloud(x, 1.0, 0.02));
}

proto::PoseMsg goodPose(uint64_t seq) {
  proto::PoseMsg pose;
  pose.vehicle_id = "tester";
  pose.session_id = kSession;
  pose.seq = seq;
  pose.stamp_ns = 1'000'000'000 + static_cast<int64_t>(seq);
  pose.position = {0.1 * static_cast<double>(seq), 0, 1};
  return pose;
}

TEST(BadInput, ServerRejectsBadSamplesAndKeepsFusingGoodOnes) {
  ServerProcess server(kDomain);
  auto participant =
      proto::Participant::create({.domain_id = kDomain, .config_file = STEREOMAP_DDS_CONFIG});
  ASSERT_TRUE(participant.ok()) << participant.error().message;
  VehicleWriters<proto::CloudFrameMsg> clouds(*participant);
  VehicleWriters<proto::PoseMsg> poses(*participant);

  ASSERT_TRUE(clouds.write(wallFrame(0, 2.05)).ok());
  ASSERT_TRUE(poses.write(goodPose(0)).ok());

  auto truncated = wallFrame(1, 2.55);
  truncated.payload.resize(truncated.payload.size() / 3);
  ASSERT_TRUE(clouds.write(truncated).ok());

  auto nan_pose = goodPose(1);
  nan_pose.position[1] = std::nan("");
  ASSERT_TRUE(poses.write(nan_pose).ok());

  auto oversize = wallFrame(2, 2.55);  // 5 MiB: over the server's 4 MiB default limit
  oversize.payload.resize(5u << 20, 0xAB);
  ASSERT_TRUE(clouds.write(oversize).ok());

  auto tilted = wallFrame(3, 2.55);
  tilted.sensor_orientation = {0.5, 0.5, 0.5, 0.9};
  ASSERT_TRUE(clouds.write(tilted).ok());

  // Enumerations are integers on the wire: unknown values reach the server, which counts them.
  auto unknown_encoding = wallFrame(5, 2.55);
  unknown_encoding.encoding = static_cast<proto::CloudEncoding>(7);
  ASSERT_TRUE(clouds.write(unknown_encoding).ok());
  auto unknown_state = goodPose(3);
  unknown_state.tracking_state = static_cast<proto::TrackingState>(9);
  ASSERT_TRUE(poses.write(unknown_state).ok());

  ASSERT_TRUE(clouds.write(wallFrame(4, 3.05)).ok());
  ASSERT_TRUE(poses.write(goodPose(2)).ok());

  std::string metrics;
  const bool counted = waitUntil(30s, [&] {
    metrics = server.get("/metrics").body;
    return seriesValue(metrics, "stereomap_session_frames_fused{session=\"bad-input\"}") == 2 &&
           seriesValue(metrics,
                       "stereomap_samples_rejected_total{topic=\"Pose\",reason=\"non_finite\"}") ==
               1 &&
           seriesValue(metrics, "stereomap_samples_accepted_total{topic=\"Pose\"}") == 2;
  });
  ASSERT_TRUE(counted) << metrics << "\n" << server.log();
  EXPECT_EQ(seriesValue(
                metrics,
                "stereomap_samples_rejected_total{topic=\"CloudFrame\",reason=\"decode_failed\"}"),
            1);
  EXPECT_EQ(
      seriesValue(metrics,
                  "stereomap_samples_rejected_total{topic=\"CloudFrame\",reason=\"oversize\"}"),
      1);
  EXPECT_EQ(seriesValue(
                metrics,
                "stereomap_samples_rejected_total{topic=\"CloudFrame\",reason=\"bad_quaternion\"}"),
            1);
  EXPECT_EQ(seriesValue(metrics, "stereomap_samples_accepted_total{topic=\"CloudFrame\"}"), 2);
  for (const char* topic : {"CloudFrame", "Pose"}) {
    EXPECT_EQ(seriesValue(metrics, std::string("stereomap_samples_rejected_total{topic=\"") +
                                       topic + "\",reason=\"bad_enum\"}"),
              1)
        << topic;
  }

  // The good frames are in the map: both walls, nothing of the rejected ones at x = 2.55.
  const auto session = nlohmann::json::parse(server.get("/api/sessions/" + kSession).body);
  EXPECT_EQ(session["frames"], 2);
  EXPECT_EQ(session["poses"], 2);
  EXPECT_NEAR(session["bounds"]["min"][0].get<double>(), 2.0, 1e-6);
  EXPECT_NEAR(session["bounds"]["max"][0].get<double>(), 3.1, 1e-6);
  const std::string log = server.log();
  EXPECT_NE(log.find("Draco payload does not decode"), std::string::npos) << log;
  EXPECT_NE(log.find("pose position is not finite"), std::string::npos) << log;
  EXPECT_NE(log.find("exceeds the limit"), std::string::npos) << log;
  EXPECT_NE(log.find("tracking_state has unknown value 9"), std::string::npos) << log;
  EXPECT_NE(log.find("encoding has unknown value 7"), std::string::npos) << log;

  EXPECT_EQ(server.get("/healthz").status, 200);
  EXPECT_TRUE(server.process().running());
  EXPECT_EQ(server.process().stop(), 0) << "the server should stop cleanly on SIGTERM";
}

// Pose corrections (issue 18) that must never touch a map: each refused with its reason,
// none journaled; a hostile but well-formed one (every pose a kilometre off) is taken and
// fused away from the map, and the server stays healthy.
TEST(BadInput, HostileCorrectionsAreRefusedWithTheirReasons) {
  constexpr int kCorrectionDomain = 88;  // ctest runs this file's tests side by side
  ServerProcess server(kCorrectionDomain);
  auto participant = proto::Participant::create(
      {.domain_id = kCorrectionDomain, .config_file = STEREOMAP_DDS_CONFIG});
  ASSERT_TRUE(participant.ok()) << participant.error().message;
  VehicleWriters<proto::CloudFrameMsg> clouds(*participant);
  VehicleWriters<proto::PoseMsg> poses(*participant);
  VehicleWriters<proto::PoseCorrectionMsg> corrections(*participant);
  for (uint64_t seq = 0; seq < 3; ++seq) {
    ASSERT_TRUE(clouds.write(wallFrame(seq, 2.05 + 0.5 * static_cast<double>(seq))).ok());
    ASSERT_TRUE(poses.write(goodPose(seq)).ok());
  }
  ASSERT_TRUE(waitUntil(30s, [&] {
    return server.get("/api/sessions/" + kSession).body.find("\"poses\":3") != std::string::npos;
  })) << server.log();

  // One vehicle id per case: each is its own DDS instance (keep-last 1), so all arrive.
  auto correction = [](const std::string& vehicle, const std::string& session) {
    proto::PoseCorrectionMsg c;
    c.vehicle_id = vehicle;
    c.session_id = session;
    c.seq = 1;
    c.stamp_ns = 5;
    c.keyframes.push_back({goodPose(1).stamp_ns, {0.1, 0, 1}, {0, 0, 0, 1}});
    return c;
  };
  auto bad_id = correction("tester", "../../etc");
  auto empty = correction("empty", kSession);
  empty.keyframes.clear();
  auto nan = correction("nan", kSession);
  nan.keyframes[0].position[2] = std::nan("");
  auto backwards = correction("backwards", kSession);
  backwards.keyframes.push_back({goodPose(0).stamp_ns, {0, 0, 1}, {0, 0, 0, 1}});
  auto strangers = correction("stranger", kSession);  // a vehicle that sent no pose
  auto nowhere = correction("tester", "no-such-session");
  for (const auto* c : {&bad_id, &empty, &nan, &backwards, &strangers, &nowhere}) {
    ASSERT_TRUE(corrections.write(*c).ok());
  }
  auto far = correction("tester", kSession);  // well formed, but a kilometre off
  far.keyframes[0].position = {1000.1, 0, 1};
  ASSERT_TRUE(corrections.write(far).ok());

  auto rejected = [](const std::string& metrics, const std::string& reason) {
    return seriesValue(
        metrics,
        "stereomap_samples_rejected_total{topic=\"PoseCorrection\",reason=\"" + reason + "\"}");
  };
  std::string metrics;
  const bool counted = waitUntil(30s, [&] {
    metrics = server.get("/metrics").body;
    return rejected(metrics, "bad_id") == 1 && rejected(metrics, "empty") == 1 &&
           rejected(metrics, "non_finite") == 1 && rejected(metrics, "bad_stamp") == 1 &&
           rejected(metrics, "unknown_poses") == 2 &&
           seriesValue(metrics, "stereomap_samples_accepted_total{topic=\"PoseCorrection\"}") == 1;
  });
  EXPECT_TRUE(counted) << metrics << "\n" << server.log();
  nlohmann::json status;
  ASSERT_TRUE(waitUntil(30s,
                        [&] {
                          status =
                              nlohmann::json::parse(server.get("/api/sessions/" + kSession).body);
                          return status["refusions"] == 1 && status["refusing"] == false;
                        }))
      << status.dump() << "\n"
      << server.log();
  EXPECT_EQ(status["corrections"], 1);
  EXPECT_FALSE(std::filesystem::exists(server.store() + "/no-such-session"));
  // The map went where the correction said: a kilometre away.
  EXPECT_GT(status["bounds"]["min"][0].get<double>(), 1000.0) << status.dump();
  EXPECT_EQ(server.get("/healthz").status, 200);
  EXPECT_TRUE(server.process().running());
  EXPECT_EQ(server.process().stop(), 0);
}

TEST(BadInput, HostileViewersGetClearErrorsAndTheServerLivesOn) {
  constexpr int kViewerDomain = 84;
  const std::string token = "viewer-t0ken";
  const std::string token_file = makeTempDir("stereomap-ws-token") + "/token";
  std::ofstream(token_file) << token << "\n";
  ServerProcess server(kViewerDomain, {"--token-file", token_file});
  using Kind = WsMessage::Kind;

  {  // A bad token in hello: closed with the reason.
    WebSocketClient ws(server.port());
    ASSERT_EQ(ws.status(), 101);
    ws.sendText(R"({"type": "hello", "protocol": 2, "token": "guess"})");
    const auto closed = ws.read();
    ASSERT_EQ(closed.kind, Kind::kClose);
    EXPECT_EQ(closed.close_code, 1008);
    EXPECT_NE(closed.payload.find("token"), std::string::npos) << closed.payload;
  }
  {  // Anything before hello: closed.
    WebSocketClient ws(server.port());
    ws.sendText(R"({"type": "subscribe", "session": "x"})");
    EXPECT_EQ(ws.read().kind, Kind::kClose);
  }
  {  // An old viewer (protocol 1): told which protocol this server speaks.
    WebSocketClient ws(server.port(), "/ws?token=" + token);
    ws.sendText(R"({"type": "hello", "protocol": 1})");
    const auto closed = ws.read();
    ASSERT_EQ(closed.kind, Kind::kClose);
    EXPECT_EQ(closed.close_code, 1002);
    EXPECT_NE(closed.payload.find("protocol 2"), std::string::npos) << closed.payload;
  }
  {  // With the token: every bad message answered, the connection kept.
    WebSocketClient ws(server.port());
    ws.sendText(R"({"type": "hello", "protocol": 2, "token": ")" + token + R"("})");
    ASSERT_EQ(ws.readUntil("\"hello\"").kind, Kind::kText);
    ASSERT_EQ(ws.readUntil("\"sessions\"").kind, Kind::kText);
    const std::vector<std::pair<std::string, std::string>> bad = {
        {"{\"type\": ", "not a JSON object"},
        {"[1, 2]", "not a JSON object"},
        {R"({"type": "launch"})", "unknown message type"},
        {R"({"type": 7})", "a message needs"},
        {R"({"type": "subscribe", "session": "no-such-flight"})", "no session 'no-such-flight'"},
        {R"({"type": "subscribe", "session": "../../etc/passwd"})", "subscribe wants"},
        {R"({"type": "view", "eye": [1, 2, 3]})", "subscribe to a session first"},
        {std::string(100, '[') + std::string(100, ']'), "nested too deeply"},
    };
    for (const auto& [text, expected] : bad) {
      SCOPED_TRACE(text.substr(0, 40));
      ASSERT_TRUE(ws.sendText(text));
      const auto answer = ws.readUntil("\"error\"");
      ASSERT_EQ(answer.kind, Kind::kText);
      EXPECT_NE(answer.payload.find(expected), std::string::npos) << answer.payload;
    }
    ASSERT_TRUE(ws.sendBinary(std::string(100, '\x01')));
    EXPECT_NE(ws.readUntil("\"error\"").payload.find("binary"), std::string::npos);
    ws.sendText(R"({"type": "ping", "t": 5})");
    EXPECT_EQ(ws.readUntil("pong").kind, Kind::kText);  // still talking
  }
  {  // A frame over the 64 kB limit: the connection goes.
    WebSocketClient ws(server.port(), "/ws?token=" + token);
    ws.sendText(R"({"type": "hello", "protocol": 2})");
    ws.readUntil("\"sessions\"");
    ws.sendText(R"({"type": "ping", "pad": ")" + std::string(200'000, 'x') + "\"}");
    const auto after = ws.readUntil("pong", 5s);
    EXPECT_NE(after.kind, Kind::kText);  // closed (1009) or dropped, never answered
  }
  {  // An unmasked client frame breaks RFC 6455: the connection goes.
    WebSocketClient ws(server.port(), "/ws?token=" + token);
    ws.sendFrame(0x1, R"({"type": "hello", "protocol": 2})", /*masked=*/false);
    EXPECT_NE(ws.readUntil("\"hello\"", 5s).kind, Kind::kText);
  }
  // The server is up and serves the next viewer as if nothing happened.
  EXPECT_EQ(server.get("/healthz").status, 200);
  WebSocketClient ws(server.port(), "/ws?token=" + token);
  ws.sendText(R"({"type": "hello", "protocol": 2})");
  EXPECT_EQ(ws.readUntil("\"sessions\"").kind, Kind::kText);
  EXPECT_TRUE(server.process().running());
  std::filesystem::remove_all(std::filesystem::path(token_file).parent_path());
}

}  // namespace
}  // namespace stereomap::testing
