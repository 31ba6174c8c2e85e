// Protocol 2 without the network: handshake, subscriptions, views, pushes, coalescing and
// the closing of stuck or hostile viewers, over a real MapServer fusing real clouds.
#include "server/viewers/viewer_hub.hpp"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <algorithm>
#include <map>

#include "common/time.hpp"
#include "proto/wire_size.hpp"
#include "testing/synthetic.hpp"

namespace stereomap::viewers {
namespace {

using nlohmann::json;
using proto::tiles::TileCells;
using tiles::TileKey;

// A wall 2 m (+ 0.3 m per `wall`) in front of the camera.
proto::CloudFrameMsg wallFrame(const std::string& session, int seq, int wall = -1) {
  return testing::planeFrame("v1", session, static_cast<uint64_t>(seq),
                             testing::planeCloud(2.05 + 0.3 * (wall < 0 ? seq : wall), 0.5, 0.03));
}

proto::PoseMsg pose(const std::string& session, int seq) {
  auto msg = testing::poseAt(session, 0.1 * seq, 1000 + seq);
  msg.seq = static_cast<uint64_t>(seq);
  return msg;
}

// What a viewer holds after applying what it was sent: level-0 cells by tile, and texts.
struct Received {
  std::map<TileKey, TileCells> tiles;
  std::vector<json> texts;
  size_t binary = 0;
  std::vector<json> ofType(const std::string& type) const {
    std::vector<json> out;
    for (const auto& t : texts)
      if (t["type"] == type) out.push_back(t);
    return out;
  }
};

void drain(ViewerHub& hub, ViewerHub::Id id, Received& into) {
  while (auto message = hub.next(id, common::nowNs())) {
    if (message->binary) {
      auto tile = proto::tiles::decodeTile(*message->bytes);
      ASSERT_TRUE(tile.ok()) << tile.error().message;
      ++into.binary;
      if (tile->cells.size() == 0) {
        into.tiles.erase(tile->header.key);
      } else {
        into.tiles[tile->header.key] = tile->cells;
      }
    } else {
      into.texts.push_back(json::parse(*message->bytes));
    }
    hub.written(id);
  }
}

std::map<TileKey, TileCells> truth(const core::Session& session) {
  std::map<TileKey, TileCells> out;
  for (const auto& info : session.tiles().list())
    out[info.key] = session.tiles().find(info.key)->cells(0);
  return out;
}

const std::string kHello = R"({"type": "hello", "protocol": 2})";
// Every tile at level 0: a huge budget and a tiny screen-space error.
const std::string kFineView =
    R"({"type": "view", "id": 7, "eye": [0, 0, 1], "budget": 10000000, "error": 0.25})";

// A viewer that says hello, subscribes to session "s" and asks for every tile at level 0;
// what it was sent so far is in `got`.
ViewerHub::Id watchEverything(ViewerHub& hub, Received& got) {
  const auto id = hub.connect(true, common::nowNs());
  hub.receive(id, kHello, 0);
  hub.receive(id, R"({"type": "subscribe", "session": "s"})", 0);
  hub.receive(id, kFineView, 0);
  drain(hub, id, got);
  return id;
}

size_t posesIn(const Received& got) {
  size_t poses = 0;
  for (const auto& m : got.ofType("poses")) poses += m["poses"].size();
  return poses;
}

// Session "s" with one wall fused, and a hub serving it.
class OneWall : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(server.ingest(wallFrame("s", 0)));
    server.find("s")->waitUntilIdle();
  }
  core::MapServer server{{.resolution = 0.1}};
  ViewerHub hub{server, nullptr, {}};
};

TEST_F(OneWall, EarlyAndLateViewersHoldExactlyTheServersMap) {
  Received early_got;
  const auto early = watchEverything(hub, early_got);
  ASSERT_EQ(early_got.ofType("hello").size(), 1u);
  EXPECT_EQ(early_got.ofType("hello")[0]["protocol"], 2);
  ASSERT_EQ(early_got.ofType("sessions").size(), 1u);
  ASSERT_EQ(early_got.ofType("subscribed").size(), 1u);
  ASSERT_EQ(early_got.ofType("view_done").size(), 1u);
  EXPECT_EQ(early_got.ofType("view_done")[0]["id"], 7);
  EXPECT_EQ(early_got.tiles, truth(*server.find("s")));

  for (int frame = 1; frame < 5; ++frame) {
    ASSERT_TRUE(server.ingest(wallFrame("s", frame)));
    ASSERT_TRUE(server.ingest(pose("s", frame)));
    server.find("s")->waitUntilIdle();
    hub.poll(common::nowNs());
    drain(hub, early, early_got);
  }
  const auto expected = truth(*server.find("s"));
  size_t voxels = 0;
  for (const auto& [key, cells] : expected) voxels += cells.size();
  EXPECT_GT(voxels, 200u);
  EXPECT_EQ(early_got.tiles, expected);
  const auto markers = early_got.ofType("map");
  ASSERT_FALSE(markers.empty());
  EXPECT_EQ(markers.back()["voxels"], voxels);
  EXPECT_GT(markers.back()["changed_ms"].get<double>(), 1.7e12);  // Unix time, in ms
  EXPECT_EQ(posesIn(early_got), 4u);

  Received late_got;
  const auto late = watchEverything(hub, late_got);
  EXPECT_EQ(late_got.tiles, expected);
  EXPECT_EQ(posesIn(late_got), 4u);
  // The trajectory on request, from an index.
  hub.receive(late, R"({"type": "trajectory", "from": 2})", 0);
  Received asked;
  drain(hub, late, asked);
  ASSERT_EQ(asked.ofType("poses").size(), 1u);
  EXPECT_EQ(asked.ofType("poses")[0]["poses"].size(), 2u);
  EXPECT_EQ(asked.ofType("trajectory_done")[0]["poses"], 2);
}

// A viewer's poses/s, clouds/s and link kB/s come from its session's counts over time: the
// poll after each live sample brings every viewer the status with the counts as they are then,
// so the last one received holds until another comes; a poll after nothing new sends none.
TEST_F(OneWall, ThePollAfterEachLiveSampleBringsTheSessionsCounts) {
  Received got;
  const auto id = watchEverything(hub, got);
  hub.poll(common::nowNs());
  drain(hub, id, got);
  const auto statusNow = [&] {
    got.texts.clear();
    hub.poll(common::nowNs());
    drain(hub, id, got);
    const auto statuses = got.ofType("session");
    return statuses.size() == 1 ? statuses[0] : json();
  };
  size_t link_bytes = proto::wireBytes(wallFrame("s", 0));
  for (int seq = 1; seq <= 3; ++seq) {
    ASSERT_TRUE(server.ingest(pose("s", seq)));
    link_bytes += proto::wireBytes(pose("s", seq));
    const json status = statusNow();
    ASSERT_TRUE(status.is_object()) << "pose " << seq << ": no single status after it";
    EXPECT_EQ(status["poses"], seq);
    EXPECT_EQ(status["frames_received"], 1);
    EXPECT_EQ(status["bytes_received"], link_bytes);
  }
  ASSERT_TRUE(server.ingest(wallFrame("s", 1)));
  link_bytes += proto::wireBytes(wallFrame("s", 1));
  server.find("s")->waitUntilIdle();
  const json status = statusNow();
  ASSERT_TRUE(status.is_object());
  EXPECT_EQ(status["frames_received"], 2);
  EXPECT_EQ(status["bytes_received"], link_bytes);
  EXPECT_TRUE(statusNow().is_null());  // nothing changed
}

// A vehicle's pose correction changes poses the viewer already has: every pose comes again,
// corrected, the first message with reset (the viewer replaces its trajectory).
TEST_F(OneWall, ACorrectedTrajectoryIsSentAgainWhole) {
  for (int seq = 1; seq < 4; ++seq) ASSERT_TRUE(server.ingest(pose("s", seq)));
  Received got;
  const auto id = watchEverything(hub, got);
  EXPECT_EQ(posesIn(got), 3u);
  proto::PoseCorrectionMsg correction;
  correction.vehicle_id = "v1";
  correction.session_id = "s";
  correction.seq = 1;
  correction.stamp_ns = 2000;
  correction.keyframes.push_back({pose("s", 2).stamp_ns, {0.2, 1.0, 0}, {0, 0, 0, 1}});
  ASSERT_TRUE(server.ingest(correction));
  server.find("s")->waitUntilIdle();
  Received after;
  hub.poll(common::nowNs());
  drain(hub, id, after);
  const auto poses = after.ofType("poses");
  ASSERT_EQ(poses.size(), 1u);
  EXPECT_TRUE(poses[0]["reset"].get<bool>());
  ASSERT_EQ(poses[0]["poses"].size(), 3u);
  for (const auto& p : poses[0]["poses"]) EXPECT_DOUBLE_EQ(p[2].get<double>(), 1.0);  // y moved
  hub.poll(common::nowNs());
  Received quiet;
  drain(hub, id, quiet);
  EXPECT_EQ(posesIn(quiet), 0u);  // once
}

// Poses of each vehicle in what a viewer was sent: stamps in order, and how many messages
// replaced what it held (reset), which must be the vehicle's first.
struct VehiclePoses {
  std::vector<double> stamps;
  size_t resets = 0;
  bool reset_first = false;
};
std::map<std::string, VehiclePoses> posesByVehicle(const Received& got) {
  std::map<std::string, VehiclePoses> out;
  for (const auto& m : got.ofType("poses")) {
    auto& v = out[m["vehicle"].get<std::string>()];
    if (m["reset"].get<bool>()) {
      v.reset_first = v.reset_first || v.stamps.empty();
      ++v.resets;
    }
    for (const auto& p : m["poses"]) v.stamps.push_back(p[0].get<double>());
  }
  return out;
}

// A long flight's trajectory is several times the cap on a viewer's unsent messages. It is
// made into messages as the viewer reads them: a subscribe gets it whole, in order, and a
// correction (every pose again) does not close the viewer for being too slow.
TEST(ViewerHub, ALongTrajectoryIsStreamedWithinTheCap) {
  core::MapServer server({.resolution = 0.1});
  constexpr int kPoses = 15'000;  // per vehicle: 30,000 poses, about 1.6 MB of JSON
  for (int seq = 1; seq <= kPoses; ++seq) {
    for (const char* vehicle : {"v1", "v2"}) {
      auto msg = pose("s", seq);
      msg.vehicle_id = vehicle;
      ASSERT_TRUE(server.ingest(msg));
    }
  }
  ViewerHub hub(server, nullptr, {.max_queued_bytes = 1u << 20});
  const auto id = hub.connect(true, 0);
  hub.receive(id, kHello, 0);
  hub.receive(id, R"({"type": "subscribe", "session": "s"})", 0);
  for (const char* vehicle : {"v1", "v2"}) {  // pushed while the stream is unsent: after it
    auto msg = pose("s", kPoses + 1);
    msg.vehicle_id = vehicle;
    ASSERT_TRUE(server.ingest(msg));
  }
  hub.poll(common::nowNs());
  Received got;
  drain(hub, id, got);
  ASSERT_FALSE(hub.closing(id));
  for (const auto& [vehicle, poses] : posesByVehicle(got)) {
    SCOPED_TRACE(vehicle);
    ASSERT_EQ(poses.stamps.size(), static_cast<size_t>(kPoses + 1));
    EXPECT_TRUE(std::is_sorted(poses.stamps.begin(), poses.stamps.end()));
    EXPECT_EQ(poses.resets, 1u);
    EXPECT_TRUE(poses.reset_first);
  }
  EXPECT_EQ(posesByVehicle(got).size(), 2u);

  proto::PoseCorrectionMsg correction;
  correction.vehicle_id = "v1";
  correction.session_id = "s";
  correction.seq = 1;
  correction.stamp_ns = pose("s", kPoses + 1).stamp_ns;
  correction.keyframes.push_back({pose("s", 2).stamp_ns, {0.2, 1.0, 0}, {0, 0, 0, 1}});
  ASSERT_TRUE(server.ingest(correction));
  server.find("s")->waitUntilIdle();
  hub.poll(common::nowNs());
  ASSERT_FALSE(hub.closing(id)) << hub.closing(id)->reason;
  Received again;
  drain(hub, id, again);
  const auto resent = posesByVehicle(again);
  ASSERT_EQ(resent.size(), 2u);
  for (const auto& [vehicle, poses] : resent) {
    SCOPED_TRACE(vehicle);
    EXPECT_EQ(poses.stamps.size(), static_cast<size_t>(kPoses + 1));
    EXPECT_EQ(poses.resets, 1u);
    EXPECT_TRUE(poses.reset_first);
  }
  // The trajectory on request, one vehicle from an index: its poses and the count asked.
  hub.receive(id, R"({"type": "trajectory", "vehicle": "v2", "from": 100})", 0);
  Received asked;
  drain(hub, id, asked);
  const auto v2 = posesByVehicle(asked);
  ASSERT_EQ(v2.size(), 1u);
  EXPECT_EQ(v2.at("v2").stamps.size(), static_cast<size_t>(kPoses + 1 - 50));
  EXPECT_EQ(v2.at("v2").resets, 0u);
  ASSERT_EQ(asked.ofType("trajectory_done").size(), 1u);
  EXPECT_EQ(asked.ofType("trajectory_done")[0]["poses"], kPoses + 1 - 50);  // those sent
  EXPECT_EQ(asked.texts.back()["type"], "trajectory_done");
}

// Corrections that come while a viewer has not yet read the trajectory replace what is
// queued instead of piling up copies of it; leaving the subscription drops it.
TEST(ViewerHub, CorrectionsWhileATrajectoryIsUnsentReplaceIt) {
  core::MapServer server({.resolution = 0.1});
  constexpr int kPoses = 25'000;  // more than one message's worth
  for (int seq = 1; seq <= kPoses; ++seq) ASSERT_TRUE(server.ingest(pose("s", seq)));
  ViewerHub hub(server, nullptr, {});
  const auto id = hub.connect(true, 0);
  hub.receive(id, kHello, 0);
  hub.receive(id, R"({"type": "subscribe", "session": "s"})", 0);
  for (uint64_t seq = 1; seq <= 3; ++seq) {
    proto::PoseCorrectionMsg correction;
    correction.vehicle_id = "v1";
    correction.session_id = "s";
    correction.seq = seq;
    correction.stamp_ns = pose("s", kPoses).stamp_ns;
    correction.keyframes.push_back(
        {pose("s", 2).stamp_ns, {0.2, 0.5 * static_cast<double>(seq), 0}, {0, 0, 0, 1}});
    ASSERT_TRUE(server.ingest(correction));
    server.find("s")->waitUntilIdle();
    hub.poll(common::nowNs());
  }
  Received got;
  drain(hub, id, got);
  const auto poses = posesByVehicle(got);
  ASSERT_EQ(poses.size(), 1u);
  EXPECT_EQ(poses.at("v1").stamps.size(), static_cast<size_t>(kPoses));  // once, not 4 times
  EXPECT_EQ(poses.at("v1").resets, 1u);
  EXPECT_DOUBLE_EQ(got.ofType("poses").back()["poses"].back()[2].get<double>(), 1.5);  // newest

  hub.receive(id, R"({"type": "subscribe", "session": "s"})", 0);
  ASSERT_TRUE(hub.next(id, common::nowNs()));  // "subscribed"
  hub.written(id);
  ASSERT_TRUE(hub.next(id, common::nowNs()));  // the first poses
  hub.written(id);
  hub.receive(id, R"({"type": "unsubscribe"})", 0);
  Received after;
  drain(hub, id, after);
  EXPECT_EQ(posesIn(after), 0u);
}

TEST_F(OneWall, ATileChangedManyTimesWhileUnsentIsSentOnceAtItsNewestVersion) {
  Received got;
  const auto id = watchEverything(hub, got);
  const size_t before = got.binary;
  std::set<TileKey> changed;
  uint64_t version = server.find("s")->tiles().summary().version;
  for (int frame = 1; frame < 6; ++frame) {  // the viewer reads nothing meanwhile
    ASSERT_TRUE(server.ingest(wallFrame("s", frame, frame % 2)));
    server.find("s")->waitUntilIdle();
    const auto since = server.find("s")->tiles().changedSince(version);
    ASSERT_TRUE(since);
    for (const auto& [key, v] : *since) changed.insert(key);
    version = server.find("s")->tiles().summary().version;
    hub.poll(common::nowNs());
  }
  drain(hub, id, got);
  EXPECT_EQ(got.binary - before, changed.size());  // once per tile, not once per change
  EXPECT_EQ(got.tiles, truth(*server.find("s")));
}

// A viewer that dropped tiles (its memory budget) gets them again with its next view, and
// only those.
TEST_F(OneWall, DroppedTilesComeBackWithTheNextView) {
  Received got;
  const auto id = watchEverything(hub, got);
  ASSERT_GE(got.tiles.size(), 2u);
  const TileKey dropped = got.tiles.begin()->first;
  got.tiles.erase(dropped);
  hub.receive(id, R"({"type": "drop", "session": "s", "keys": [")" + dropped.text() + R"("]})", 0);
  const size_t before = got.binary;
  hub.receive(id, kFineView, 0);
  drain(hub, id, got);
  EXPECT_EQ(got.binary - before, 1u);
  EXPECT_EQ(got.tiles, truth(*server.find("s")));
  got.texts.clear();
  hub.receive(id, R"({"type": "drop", "session": "s", "keys": ["1_2"]})", 0);
  drain(hub, id, got);
  EXPECT_EQ(got.ofType("error").size(), 1u);
}

TEST(ViewerHub, HandshakeAndTokens) {
  core::MapServer server({.resolution = 0.1});
  core::AccessList access;
  access.add(core::Role::kViewer, "t0ken", "wall");
  ViewerHub hub(server, nullptr, {.access = access});
  auto before_hello = hub.connect(false, 0);
  hub.receive(before_hello, R"({"type": "list"})", 0);
  ASSERT_TRUE(hub.closing(before_hello));
  EXPECT_EQ(hub.closing(before_hello)->code, 1008);

  auto old_protocol = hub.connect(false, 0);
  hub.receive(old_protocol, R"({"type": "hello", "protocol": 1, "token": "t0ken"})", 0);
  ASSERT_TRUE(hub.closing(old_protocol));
  EXPECT_EQ(hub.closing(old_protocol)->code, 1002);

  auto bad_token = hub.connect(false, 0);
  hub.receive(bad_token, R"({"type": "hello", "protocol": 2, "token": "guess"})", 0);
  ASSERT_TRUE(hub.closing(bad_token));
  EXPECT_NE(hub.closing(bad_token)->reason.find("token"), std::string::npos);

  auto good = hub.connect(false, 0);
  hub.receive(good, R"({"type": "hello", "protocol": 2, "token": "t0ken"})", 0);
  EXPECT_FALSE(hub.closing(good));
  auto by_upgrade = hub.connect(true, 0);  // the token came with the upgrade request
  hub.receive(by_upgrade, kHello, 0);
  EXPECT_FALSE(hub.closing(by_upgrade));

  auto silent = hub.connect(false, 0);
  hub.poll(11'000'000'000);
  ASSERT_TRUE(hub.closing(silent));
  EXPECT_NE(hub.closing(silent)->reason.find("no hello"), std::string::npos);
  EXPECT_FALSE(hub.closing(good));
}

TEST(ViewerHub, BadMessagesAreAnsweredAndTooManyClose) {
  core::MapServer server({.resolution = 0.1});
  ViewerHub hub(server, nullptr, {});
  const auto id = hub.connect(true, 0);
  hub.receive(id, kHello, 0);
  Received got;
  drain(hub, id, got);
  const std::vector<std::string> bad = {
      "{not json",
      "[1, 2, 3]",
      R"({"no_type": 1})",
      R"({"type": "teleport"})",
      R"({"type": "subscribe", "session": "../etc"})",
      R"({"type": "view", "eye": [0, 0, 1]})",  // not subscribed
      std::string(20, '[') + std::string(20, ']'),
      R"({"type": "hello", "protocol": 2})",
  };
  for (const auto& text : bad) {
    got.texts.clear();
    hub.receive(id, text, 0);
    drain(hub, id, got);
    ASSERT_EQ(got.ofType("error").size(), 1u) << text;
    EXPECT_FALSE(hub.closing(id)) << text;
  }
  got.texts.clear();
  hub.receive(id, R"({"type": "subscribe", "session": "missing"})", 0);
  drain(hub, id, got);
  ASSERT_EQ(got.ofType("error").size(), 1u);
  EXPECT_EQ(got.ofType("error")[0]["code"], "not_found");

  ASSERT_TRUE(server.ingest(wallFrame("s", 0)));
  server.find("s")->waitUntilIdle();
  hub.receive(id, R"({"type": "subscribe", "session": "s"})", 0);
  for (const char* view :
       {R"({"type": "view", "eye": [0, 0]})", R"({"type": "view", "eye": [0, 0, 1], "budget": -5})",
        R"({"type": "view", "eye": [0, 0, 1], "fov": 1e300})",
        R"({"type": "view", "eye": [0, 0, 1], "planes": [[1, 2, 3]]})"}) {
    got.texts.clear();
    hub.receive(id, view, 0);
    drain(hub, id, got);
    EXPECT_EQ(got.ofType("error").size(), 1u) << view;
  }
  for (int i = 0; i < 20 && !hub.closing(id); ++i) hub.receive(id, "nonsense", 0);
  ASSERT_TRUE(hub.closing(id));
  EXPECT_NE(hub.closing(id)->reason.find("too many bad messages"), std::string::npos);
  hub.receiveBinary(id, std::string(10, 'x'));  // after closing: ignored, no crash
}

TEST(ViewerHub, AViewerThatStopsReadingIsClosedWithAReason) {
  core::MapServer server({.resolution = 0.1});
  ViewerHub hub(server, nullptr, {.stuck_after = std::chrono::milliseconds(500)});
  const auto stuck = hub.connect(true, 0);
  const auto fine = hub.connect(true, 0);
  hub.receive(stuck, kHello, 0);
  hub.receive(fine, kHello, 0);
  ASSERT_TRUE(hub.next(stuck, 1'000'000'000));  // a write that never completes
  Received got;
  drain(hub, fine, got);
  hub.poll(1'400'000'000);
  EXPECT_FALSE(hub.closing(stuck));
  hub.poll(1'600'000'000);
  ASSERT_TRUE(hub.closing(stuck));
  EXPECT_NE(hub.closing(stuck)->reason.find("stuck"), std::string::npos);
  EXPECT_FALSE(hub.closing(fine));
  EXPECT_EQ(hub.stats().closed_stuck, 1u);
}

}  // namespace
}  // namespace stereomap::viewers
