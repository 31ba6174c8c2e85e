// The Foxglove WebSocket protocol without the network, over a real MapServer fusing real
// clouds: the handshake, channels per session (scoped and not), subscriptions and their
// first messages, coalescing, unsubscribing, and the closing of hostile, stuck or slow clients.
// (Foxglove's own client decodes what a live server sends: tests/interop/foxglove_live.mjs.)
#include "server/viewers/foxglove_hub.hpp"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <map>

#include "common/time.hpp"
#include "proto/pose_fields.hpp"
#include "server/interop/foxglove_session.hpp"
#include "testing/synthetic.hpp"

namespace stereomap::viewers {
namespace {

using nlohmann::json;

proto::CloudFrameMsg wallFrame(const std::string& session, int seq) {
  return testing::planeFrame("v1", session, static_cast<uint64_t>(seq),
                             testing::planeCloud(2.05 + 0.3 * seq, 0.5, 0.03));
}

proto::PoseMsg pose(const std::string& session, int seq) {
  auto msg = testing::poseAt(session, 0.1 * seq, 1000 + seq);
  msg.seq = static_cast<uint64_t>(seq);
  return msg;
}

struct Data {
  uint32_t subscription;
  uint64_t time;
  size_t bytes;
};

struct Received {
  std::vector<json> texts;
  std::vector<Data> data;
  std::map<std::string, uint32_t> channels;  // topic -> id
  std::vector<json> ofOp(const std::string& op) const {
    std::vector<json> out;
    for (const auto& t : texts)
      if (t["op"] == op) out.push_back(t);
    return out;
  }
  size_t from(uint32_t subscription) const {
    size_t n = 0;
    for (const auto& d : data) n += d.subscription == subscription;
    return n;
  }
};

void drain(FoxgloveHub& hub, FoxgloveHub::Id id, Received& into) {
  while (auto message = hub.next(id, common::nowNs())) {
    const std::string& bytes = *message->bytes;
    if (message->binary) {
      ASSERT_GE(bytes.size(), 13u);
      ASSERT_EQ(bytes[0], 1);  // messageData
      Data d{0, 0, bytes.size() - 13};
      for (int i = 0; i < 4; ++i) d.subscription |= uint32_t{uint8_t(bytes[1 + i])} << (8 * i);
      for (int i = 0; i < 8; ++i) d.time |= uint64_t{uint8_t(bytes[5 + i])} << (8 * i);
      into.data.push_back(d);
    } else {
      into.texts.push_back(json::parse(bytes));
      const auto& t = into.texts.back();
      if (t["op"] == "advertise") {
        for (const auto& c : t["channels"]) into.channels[c["topic"]] = c["id"];
      }
    }
    hub.written(id);
  }
}

std::string subscribe(uint32_t id, uint32_t channel) {
  return json{{"op", "subscribe"}, {"subscriptions", {{{"id", id}, {"channelId", channel}}}}}
      .dump();
}

class FlyingSession : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(server.ingest(wallFrame("s", 0)));
    ASSERT_TRUE(server.ingest(pose("s", 0)));
    server.find("s")->waitUntilIdle();
  }
  void fly(int frames) {
    for (int i = 0; i < frames; ++i, ++seq) {
      ASSERT_TRUE(server.ingest(wallFrame("s", seq)));
      ASSERT_TRUE(server.ingest(pose("s", seq)));
    }
    server.find("s")->waitUntilIdle();
  }
  core::MapServer server{{.resolution = 0.1}};
  FoxgloveHub hub{server, {.trajectory_every = std::chrono::milliseconds(0)}};
  int seq = 1;
};

TEST_F(FlyingSession, AClientIsToldTheServerAndEverySessionsChannels) {
  const auto id = hub.connect("", 0);
  Received got;
  drain(hub, id, got);
  ASSERT_GE(got.texts.size(), 2u);
  EXPECT_EQ(got.texts[0]["op"], "serverInfo");
  EXPECT_EQ(got.texts[0]["capabilities"], json::array());
  for (const char* topic :
       {"/s/tf", "/s/map", "/s/map2d", "/s/vehicles/v1/trajectory", "/s/vehicles/v1/cloud"}) {
    EXPECT_TRUE(got.channels.count(topic)) << topic;
  }
  const auto advertised = got.ofOp("advertise");
  ASSERT_FALSE(advertised.empty());
  for (const auto& channel : advertised[0]["channels"]) {
    EXPECT_EQ(channel["encoding"], "protobuf");
    EXPECT_EQ(channel["schemaEncoding"], "protobuf");
    EXPECT_TRUE(channel["schemaName"].get<std::string>().starts_with("foxglove."));
    EXPECT_GT(channel["schema"].get<std::string>().size(), 100u);
  }
  // A new session's channels come as it appears.
  ASSERT_TRUE(server.ingest(wallFrame("t", 0)));
  hub.poll(common::nowNs());
  drain(hub, id, got);
  EXPECT_TRUE(got.channels.count("/t/map"));
}

TEST_F(FlyingSession, AScopedClientSeesOneSessionNamedAsItsExport) {
  ASSERT_TRUE(server.ingest(wallFrame("other", 0)));
  const auto id = hub.connect("s", 0);
  Received got;
  drain(hub, id, got);
  EXPECT_TRUE(got.channels.count("/tf"));
  EXPECT_TRUE(got.channels.count("/map"));
  EXPECT_TRUE(got.channels.count("/vehicles/v1/trajectory"));
  for (const auto& [topic, channel] : got.channels) EXPECT_FALSE(topic.starts_with("/other"));
  // A session not loaded: a warning, and its channels once it is.
  const auto later = hub.connect("late", 0);
  Received late;
  drain(hub, later, late);
  ASSERT_EQ(late.ofOp("status").size(), 1u);
  EXPECT_TRUE(late.channels.empty());
  ASSERT_TRUE(server.ingest(wallFrame("late", 0)));
  hub.poll(common::nowNs());
  drain(hub, later, late);
  EXPECT_TRUE(late.channels.count("/map"));
}

TEST_F(FlyingSession, SubscribersGetTheNewestAtOnceThenWhatChangesUntilTheyUnsubscribe) {
  const auto id = hub.connect("s", 0);
  Received got;
  drain(hub, id, got);
  hub.receive(id, subscribe(1, got.channels.at("/map")), 0);
  hub.receive(id, subscribe(2, got.channels.at("/tf")), 0);
  hub.receive(id, subscribe(3, got.channels.at("/vehicles/v1/trajectory")), 0);
  hub.receive(id, subscribe(4, got.channels.at("/vehicles/v1/cloud")), 0);
  drain(hub, id, got);
  EXPECT_EQ(got.from(1), server.find("s")->tiles().list().size());  // an entity per tile
  EXPECT_EQ(got.from(2), 1u);                                       // the newest transform
  EXPECT_EQ(got.from(3), 1u);
  EXPECT_EQ(got.from(4), 1u);
  EXPECT_TRUE(got.ofOp("status").empty());

  fly(3);
  hub.poll(common::nowNs());
  drain(hub, id, got);
  EXPECT_EQ(got.from(2), 4u);  // every pose
  EXPECT_EQ(got.from(3), 2u);  // the path once a poll
  EXPECT_EQ(got.from(4), 2u);  // the newest cloud once a poll: older unsent ones replaced
  EXPECT_GT(got.from(1), server.find("s")->tiles().list().size());

  hub.receive(id, R"({"op": "unsubscribe", "subscriptionIds": [1, 2, 3, 4]})", 0);
  const size_t before = got.data.size();
  fly(2);
  hub.poll(common::nowNs());
  drain(hub, id, got);
  EXPECT_EQ(got.data.size(), before);
  EXPECT_TRUE(got.ofOp("status").empty());
}

// A vehicle in its own frame: its clouds reach no subscriber while it is held apart (nowhere in
// the map's frame yet); once it joins they come, placed by its alignment.
TEST_F(FlyingSession, AHeldVehiclesCloudsWaitForItsJoinAndComePlaced) {
  const auto session = server.find("s");
  ASSERT_FALSE(session->holdApart("v2", true)) << "v1 is in the map: v2 is no reference";
  auto v2Frame = [&](int i) {
    return testing::planeFrame("v2", "s", static_cast<uint64_t>(100 + i),
                               testing::planeCloud(2.0 + 0.2 * i, 0.5, 0.03));
  };
  ASSERT_TRUE(server.ingest(v2Frame(0)));
  session->waitUntilIdle();
  const auto id = hub.connect("s", 0);
  Received got;
  drain(hub, id, got);
  hub.poll(common::nowNs());
  drain(hub, id, got);
  ASSERT_TRUE(got.channels.count("/vehicles/v2/cloud")) << "advertised: it is flying";
  hub.receive(id, subscribe(7, got.channels.at("/vehicles/v2/cloud")), 0);
  ASSERT_TRUE(server.ingest(v2Frame(1)));
  session->waitUntilIdle();
  hub.poll(common::nowNs());
  drain(hub, id, got);
  EXPECT_EQ(got.from(7), 0u) << "held apart: none of its clouds";
  EXPECT_FALSE(interop::framePlacement(*session, "v2"));
  EXPECT_TRUE(interop::framePlacement(*session, "v1")->translation.isZero());

  const common::Rigid3 T{common::Quat(Eigen::AngleAxisd(1.0, common::Vec3::UnitZ())),
                         common::Vec3(4.0, -3.0, 0.5)};
  session->join("v2", T, 0.5, 0.01, /*refuse=*/true);
  ASSERT_TRUE(server.ingest(v2Frame(2)));
  session->waitUntilIdle();
  hub.poll(common::nowNs());
  drain(hub, id, got);
  EXPECT_GE(got.from(7), 1u) << "joined: its clouds come";
  const auto placed = interop::framePlacement(*session, "v2");
  ASSERT_TRUE(placed);
  EXPECT_TRUE(placed->translation.isApprox(T.translation));
  // Placed: the message is the one a vehicle in the session's frame would have sent.
  auto frame = v2Frame(3);
  auto moved = frame;
  proto::fieldsFromRigid(
      T * proto::rigidFromFields(frame.sensor_position, frame.sensor_orientation),
      moved.sensor_position, moved.sensor_orientation);
  EXPECT_EQ(interop::cloudMessage(frame, *placed)->bytes, interop::cloudMessage(moved)->bytes);
  EXPECT_NE(interop::cloudMessage(frame)->bytes, interop::cloudMessage(moved)->bytes);
}

TEST_F(FlyingSession, HostileMessagesAreAnsweredThenTheClientIsClosed) {
  const auto id = hub.connect("s", 0);
  Received got;
  drain(hub, id, got);
  const std::vector<std::string> hostile = {
      "nonsense",
      "[]",
      R"({"op": 5})",
      R"({"op": "subscribe"})",
      R"({"op": "subscribe", "subscriptions": [{"id": -1, "channelId": 1}]})",
      R"({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": 4294967296}]})",
      R"({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": 999}]})",
      R"({"op": "subscribe", "subscriptions": [{"id": 1.5, "channelId": 1}]})",
      R"({"op": "unsubscribe", "subscriptionIds": [77]})",
      R"({"op": "advertise", "channels": []})",
      R"({"op": "subscribe", "subscriptions": [[[[[[1]]]]]]})",
  };
  for (const auto& text : hostile) {
    const size_t before = got.ofOp("status").size();
    hub.receive(id, text, 0);
    drain(hub, id, got);
    EXPECT_EQ(got.ofOp("status").size(), before + 1) << text;
    EXPECT_EQ(got.ofOp("status").back()["level"], 2) << text;
  }
  EXPECT_FALSE(hub.closing(id));
  // A subscription id used twice: the second is refused, the first stays.
  hub.receive(id, subscribe(9, got.channels.at("/tf")), 0);
  hub.receive(id, subscribe(9, got.channels.at("/map")), 0);
  drain(hub, id, got);
  hub.receiveBinary(id, std::string("\x01\0\0\0\0xyz", 8));
  for (int i = 0; i < 20 && !hub.closing(id); ++i) hub.receive(id, "{", 0);
  ASSERT_TRUE(hub.closing(id));
  EXPECT_EQ(hub.closing(id)->code, 1008);
  EXPECT_NE(hub.closing(id)->reason.find("too many bad messages"), std::string::npos);
  EXPECT_FALSE(hub.next(id, 0));
}

TEST_F(FlyingSession, StuckAndSlowClientsAreClosedAndOthersGoOn) {
  FoxgloveHub small(server,
                    {.stuck_after = std::chrono::milliseconds(500), .max_queued_bytes = 1000});
  const auto stuck = small.connect("s", 0);
  const auto slow = small.connect("s", 0);
  const auto fine = small.connect("s", 0);
  Received s1, s2, s3;
  drain(small, slow, s2);
  drain(small, fine, s3);
  small.receive(slow, subscribe(1, s2.channels.at("/tf")), 0);
  small.receive(fine, subscribe(1, s3.channels.at("/tf")), 0);
  ASSERT_TRUE(small.next(stuck, 1'000'000'000));  // a write that never completes
  small.poll(1'400'000'000);
  EXPECT_FALSE(small.closing(stuck));
  small.poll(1'600'000'000);
  ASSERT_TRUE(small.closing(stuck));
  EXPECT_NE(small.closing(stuck)->reason.find("stuck"), std::string::npos);
  // `slow` reads nothing while 40 transforms (about 40 bytes each) come.
  for (int i = 0; i < 40; ++i) {
    fly(1);
    small.poll(common::nowNs());
    drain(small, fine, s3);
  }
  ASSERT_TRUE(small.closing(slow));
  EXPECT_NE(small.closing(slow)->reason.find("too slow"), std::string::npos);
  EXPECT_FALSE(small.closing(fine));
  EXPECT_EQ(s3.from(1), 41u);
  EXPECT_EQ(small.stats().closed_stuck, 2u);
}

TEST_F(FlyingSession, ASessionThatGoesIsUnadvertised) {
  const auto id = hub.connect("", 0);
  Received got;
  drain(hub, id, got);
  hub.receive(id, subscribe(1, got.channels.at("/s/tf")), 0);
  ASSERT_TRUE(server.unload("s"));
  hub.poll(common::nowNs());
  drain(hub, id, got);
  ASSERT_EQ(got.ofOp("unadvertise").size(), 1u);
  EXPECT_EQ(got.ofOp("unadvertise")[0]["channelIds"].size(), 5u);
  // Its subscription went with it: unsubscribing it now is a mistake.
  hub.receive(id, R"({"op": "unsubscribe", "subscriptionIds": [1]})", 0);
  drain(hub, id, got);
  EXPECT_EQ(got.ofOp("status").size(), 1u);
}

}  // namespace
}  // namespace stereomap::viewers
