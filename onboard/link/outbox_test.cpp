#include "onboard/link/outbox.hpp"

#include <gtest/gtest.h>

#include <variant>

#include "proto/wire_size.hpp"

namespace stereomap::link {
namespace {

constexpr int64_t kSecond = 1'000'000'000;

struct Sent {
  SpoolTopic topic;
  uint64_t seq;
  uint64_t unacked_from;
};

class OutboxTest : public ::testing::Test {
 protected:
  Outbox make(double link_bits_per_s = 0) {
    auto spool = Spool::open({});
    EXPECT_TRUE(spool.ok());
    return Outbox(std::move(spool).value(),
                  {.vehicle_id = "uav", .link_bits_per_s = link_bits_per_s, .stream = 9},
                  [this](const SpoolRecord& r) {
                    std::visit(
                        [&](const auto& m) {
                          sent_.push_back({spoolTopicOf(r), m.seq, m.unacked_from});
                          bytes_ += proto::wireBytes(m);
                        },
                        r);
                    return common::Status(common::Ok{});
                  });
  }
  static proto::PoseMsg pose() {
    proto::PoseMsg p;
    p.vehicle_id = "uav";
    p.session_id = "s";
    return p;
  }
  static proto::CloudFrameMsg cloud(size_t bytes = 10000) {
    proto::CloudFrameMsg c;
    c.vehicle_id = "uav";
    c.session_id = "s";
    c.payload.assign(bytes, 1);
    return c;
  }
  static proto::AckMsg ack(uint64_t poses, uint64_t clouds) {
    proto::AckMsg a;
    a.vehicle_id = "uav";
    a.session_id = "s";
    a.stream = 9;
    a.poses = poses;
    a.clouds = clouds;
    return a;
  }
  std::vector<Sent> sent_;
  uint64_t bytes_ = 0;
};

TEST_F(OutboxTest, NumbersEachTopicInTheStream) {
  auto outbox = make();
  for (int i = 0; i < 3; ++i) {
    auto p = pose();
    ASSERT_TRUE(outbox.send(p, 0).ok());
    EXPECT_EQ(p.stream, 9u);
    EXPECT_EQ(p.seq, static_cast<uint64_t>(i));
    EXPECT_EQ(p.unacked_from, 0u);  // seq 0 is still held
  }
  auto c = cloud();
  ASSERT_TRUE(outbox.send(c, 0).ok());
  EXPECT_EQ(c.seq, 0u);
  outbox.acknowledge(ack(2, 0));
  auto p = pose();
  ASSERT_TRUE(outbox.send(p, 0).ok());
  EXPECT_EQ(p.seq, 3u);
  EXPECT_EQ(p.unacked_from, 2u);
}

// Not acknowledged: sent again once a server is there, poses before clouds, and never before
// resend_after.
TEST_F(OutboxTest, SendsAgainWhatWasNotAcknowledged) {
  auto outbox = make();
  auto c = cloud();
  ASSERT_TRUE(outbox.send(c, 0).ok());
  for (int i = 0; i < 2; ++i) {
    auto p = pose();
    ASSERT_TRUE(outbox.send(p, 0).ok());
  }
  sent_.clear();
  outbox.resend(1 * kSecond, true);
  EXPECT_TRUE(sent_.empty());
  outbox.resend(10 * kSecond, false);  // no server: nothing goes
  EXPECT_TRUE(sent_.empty());
  outbox.resend(10 * kSecond, true);
  ASSERT_EQ(sent_.size(), 3u);
  EXPECT_EQ(sent_[0].topic, SpoolTopic::kPose);
  EXPECT_EQ(sent_[1].topic, SpoolTopic::kPose);
  EXPECT_EQ(sent_[2].topic, SpoolTopic::kCloud);
  EXPECT_EQ(outbox.stats().resent, 3u);
  outbox.acknowledge(ack(2, 1));
  EXPECT_TRUE(outbox.caughtUp());
}

TEST_F(OutboxTest, AcknowledgementsOfOtherVehiclesAreIgnored) {
  auto outbox = make();
  auto p = pose();
  ASSERT_TRUE(outbox.send(p, 0).ok());
  auto other = ack(1, 0);
  other.vehicle_id = "someone-else";
  outbox.acknowledge(other);
  EXPECT_EQ(outbox.stats().foreign_acks, 1u);
  EXPECT_FALSE(outbox.caughtUp());
}

// The server closed the session: nothing more is sent, live or again; with keep_when_closed
// every sample stays in the spool (those made after too), without it they are given up. An
// answer about closing counts nothing as acknowledged.
TEST_F(OutboxTest, AClosedSessionGetsNothingMoreAndItsSamplesAreKeptOrGivenUp) {
  for (const bool keep : {true, false}) {
    auto spool = Spool::open({});
    ASSERT_TRUE(spool.ok());
    sent_.clear();
    Outbox outbox(std::move(spool).value(),
                  {.vehicle_id = "uav", .stream = 9, .keep_when_closed = keep},
                  [this](const SpoolRecord& r) {
                    sent_.push_back({spoolTopicOf(r), 0, 0});
                    return common::Status(common::Ok{});
                  });
    for (int i = 0; i < 3; ++i) {
      auto p = pose();
      ASSERT_TRUE(outbox.send(p, 0).ok());
    }
    auto closing = ack(0, 0);
    closing.status = proto::AckStatus::kSessionClosed;
    closing.reason = "closed by an operator";
    outbox.acknowledge(closing);  // counts nothing
    EXPECT_EQ(outbox.spool().stats().held, 3u);
    EXPECT_EQ(outbox.closeSession("s"), keep ? 0u : 3u) << keep;
    EXPECT_TRUE(outbox.closed());
    const size_t sent_before = sent_.size();
    auto p = pose();
    ASSERT_TRUE(outbox.send(p, 0).ok());
    EXPECT_EQ(p.seq, 3u);  // still numbered in the stream
    auto c = cloud();
    ASSERT_TRUE(outbox.send(c, 0).ok());
    outbox.resend(100 * kSecond, true);
    EXPECT_EQ(sent_.size(), sent_before) << "nothing sent after closing";
    EXPECT_EQ(outbox.stats().held_back, 2u);
    EXPECT_EQ(outbox.spool().stats().held, keep ? 5u : 0u) << keep;
    EXPECT_EQ(outbox.spool().stats().dropped_closed, keep ? 0u : 3u) << keep;
  }
}

// Under a budget, samples sent again take what the live ones leave of the link's rate.
TEST_F(OutboxTest, SendingAgainStaysWithinTheLinksBudget) {
  const double link = 1e6;  // bits per second
  auto outbox = make(link);
  for (int i = 0; i < 200; ++i) {
    auto c = cloud(10000);
    ASSERT_TRUE(outbox.send(c, 0).ok());  // an outage's backlog: 2 MB
  }
  bytes_ = 0;
  // Ten seconds of catching up at 10 Hz while the live stream takes 200 kbit/s.
  for (int frame = 0; frame < 100; ++frame) {
    const int64_t now = 10 * kSecond + frame * kSecond / 10;
    outbox.charge(2500, now);
    outbox.resend(now, true);
  }
  const double resent_bits_per_s = static_cast<double>(bytes_) * 8 / 10;
  EXPECT_GT(resent_bits_per_s, 0.5 * (0.9 * link - 200e3));
  EXPECT_LE(resent_bits_per_s, 0.9 * link - 200e3 + 0.25 * link / 10 * 8 / 8);
}

}  // namespace
}  // namespace stereomap::link
