#include "server/core/receipts.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <random>

namespace stereomap::core {
namespace {

SampleId sample(uint64_t seq, uint64_t unacked_from = 0, uint64_t stream = 7) {
  return {"uav", stream, seq, unacked_from, 1000 + static_cast<int64_t>(seq)};
}

// Re-sent in any order, any number of times: each seq is taken once, and the acknowledgement
// counts exactly the seqs taken from 0 with none missing.
TEST(Receipts, EachSeqIsTakenOnceInAnyOrder) {
  Receipts receipts;
  std::vector<uint64_t> order;
  for (uint64_t seq = 0; seq < 500; ++seq) order.insert(order.end(), 3, seq);
  std::shuffle(order.begin(), order.end(), std::mt19937(1));
  std::vector<int> taken(500, 0);
  for (uint64_t seq : order)
    taken[seq] += receipts.claim(ReceiptTopic::kCloud, sample(seq)) == Claim::kNew;
  EXPECT_TRUE(std::all_of(taken.begin(), taken.end(), [](int n) { return n == 1; }));
  const auto ack = receipts.ack("uav", 7);
  EXPECT_EQ(ack.clouds, 500u);
  EXPECT_EQ(ack.poses, 0u);
}

TEST(Receipts, TheCountStopsAtTheFirstMissingSeq) {
  Receipts receipts;
  for (uint64_t seq : {0, 1, 2, 4, 5}) receipts.claim(ReceiptTopic::kPose, sample(seq));
  EXPECT_EQ(receipts.ack("uav", 7).poses, 3u);
  EXPECT_EQ(receipts.check(ReceiptTopic::kPose, sample(4)), Claim::kDuplicate);
  EXPECT_EQ(receipts.check(ReceiptTopic::kPose, sample(3)), Claim::kNew);
  receipts.claim(ReceiptTopic::kPose, sample(3));
  EXPECT_EQ(receipts.ack("uav", 7).poses, 6u);
}

// A sender that gave seq 3 up (its spool was full) says so with unacked_from: the count passes
// the gap, and the seq it gave up counts as a duplicate if it ever comes.
TEST(Receipts, UnackedFromPassesWhatTheSenderGaveUp) {
  Receipts receipts;
  for (uint64_t seq : {0, 1, 2, 4}) receipts.claim(ReceiptTopic::kCloud, sample(seq));
  EXPECT_EQ(receipts.ack("uav", 7).clouds, 3u);
  receipts.claim(ReceiptTopic::kCloud, sample(5, /*unacked_from=*/4));
  EXPECT_EQ(receipts.ack("uav", 7).clouds, 6u);
  EXPECT_EQ(receipts.takeGivenUp(ReceiptTopic::kCloud), 1u);  // seq 3
  EXPECT_EQ(receipts.takeGivenUp(ReceiptTopic::kCloud), 0u);
  EXPECT_EQ(receipts.check(ReceiptTopic::kCloud, sample(3)), Claim::kDuplicate);
  // unacked_from beyond the sample's own seq is read as the seq: the sample itself is held,
  // nothing below it.
  receipts.claim(ReceiptTopic::kCloud, sample(8, /*unacked_from=*/100));
  EXPECT_EQ(receipts.ack("uav", 7).clouds, 9u);
  EXPECT_EQ(receipts.check(ReceiptTopic::kCloud, sample(7)), Claim::kDuplicate);
  EXPECT_EQ(receipts.check(ReceiptTopic::kCloud, sample(9)), Claim::kNew);
}

TEST(Receipts, StreamsAndVehiclesAreApart) {
  Receipts receipts;
  EXPECT_EQ(receipts.claim(ReceiptTopic::kPose, sample(0, 0, 7)), Claim::kNew);
  EXPECT_EQ(receipts.claim(ReceiptTopic::kPose, sample(0, 0, 8)), Claim::kNew);
  SampleId other = sample(0, 0, 7);
  other.vehicle = "uav2";
  EXPECT_EQ(receipts.claim(ReceiptTopic::kPose, other), Claim::kNew);
  EXPECT_EQ(receipts.claim(ReceiptTopic::kCloud, sample(0, 0, 7)), Claim::kNew);
  EXPECT_EQ(receipts.claim(ReceiptTopic::kPose, sample(0, 0, 7)), Claim::kDuplicate);
}

TEST(Receipts, ANewerCorrectionCountsTheOlderOnesTaken) {
  Receipts receipts;
  EXPECT_EQ(receipts.claim(ReceiptTopic::kCorrection, sample(4)), Claim::kNew);
  EXPECT_EQ(receipts.ack("uav", 7).corrections, 5u);
  EXPECT_EQ(receipts.claim(ReceiptTopic::kCorrection, sample(2)), Claim::kDuplicate);
  EXPECT_EQ(receipts.claim(ReceiptTopic::kCorrection, sample(6)), Claim::kNew);
  EXPECT_EQ(receipts.ack("uav", 7).corrections, 7u);
}

// Stream 0 (journals from before streams): new when newer in seq or stamp, as before.
TEST(Receipts, StreamZeroKeepsTheSeqOrStampRule) {
  Receipts receipts;
  auto legacy = [](uint64_t seq, int64_t stamp) { return SampleId{"uav", 0, seq, 0, stamp}; };
  EXPECT_EQ(receipts.claim(ReceiptTopic::kEvent, legacy(0, 100)), Claim::kNew);
  EXPECT_EQ(receipts.claim(ReceiptTopic::kEvent, legacy(0, 100)), Claim::kDuplicate);
  EXPECT_EQ(receipts.claim(ReceiptTopic::kEvent, legacy(0, 200)), Claim::kNew);  // the end event
  EXPECT_EQ(receipts.claim(ReceiptTopic::kEvent, legacy(0, 150)), Claim::kDuplicate);
  EXPECT_TRUE(receipts.takeAcks().empty());  // nothing to acknowledge to a sender without streams
}

// Acknowledgements are due when receipts change or a sample comes again (its sender has not
// heard), not otherwise.
TEST(Receipts, AcksAreDueOnChangeAndOnDuplicates) {
  Receipts receipts;
  EXPECT_TRUE(receipts.takeAcks().empty());
  receipts.claim(ReceiptTopic::kPose, sample(0));
  receipts.claim(ReceiptTopic::kCloud, sample(0));
  auto acks = receipts.takeAcks();
  ASSERT_EQ(acks.size(), 1u);
  EXPECT_EQ(acks[0].vehicle_id, "uav");
  EXPECT_EQ(acks[0].stream, 7u);
  EXPECT_EQ(acks[0].poses, 1u);
  EXPECT_EQ(acks[0].clouds, 1u);
  EXPECT_TRUE(receipts.takeAcks().empty());
  EXPECT_EQ(receipts.check(ReceiptTopic::kPose, sample(0)), Claim::kDuplicate);
  EXPECT_EQ(receipts.takeAcks().size(), 1u);
}

// Seqs taken above a gap are bounded: a sender far ahead (or a forged seq) is told to wait, and
// memory stays bounded.
TEST(Receipts, TheWindowAboveAGapIsBounded) {
  Receipts receipts;
  for (uint64_t seq = 1; seq <= kReceiptWindow; ++seq) {
    ASSERT_EQ(receipts.claim(ReceiptTopic::kPose, sample(seq)), Claim::kNew);
  }
  EXPECT_EQ(receipts.claim(ReceiptTopic::kPose, sample(kReceiptWindow + 1)), Claim::kOutOfWindow);
  EXPECT_EQ(receipts.claim(ReceiptTopic::kPose, sample(0)), Claim::kNew);  // the gap closes
  EXPECT_EQ(receipts.ack("uav", 7).poses, kReceiptWindow + 1);
  EXPECT_EQ(receipts.claim(ReceiptTopic::kPose, sample(kReceiptWindow + 1)), Claim::kNew);
}

// A hostile seq at the end of the range is refused rather than wrapping a count to 0 (which
// would take every earlier sample again).
TEST(Receipts, TheLastSeqIsRefused) {
  Receipts receipts;
  EXPECT_EQ(receipts.claim(ReceiptTopic::kCorrection, sample(UINT64_MAX)), Claim::kOutOfWindow);
  EXPECT_EQ(receipts.claim(ReceiptTopic::kPose, sample(UINT64_MAX, UINT64_MAX)),
            Claim::kOutOfWindow);
  EXPECT_EQ(receipts.claim(ReceiptTopic::kCorrection, sample(3)), Claim::kNew);
  EXPECT_EQ(receipts.claim(ReceiptTopic::kCorrection, sample(2)), Claim::kDuplicate);
}

TEST(Receipts, StreamsAreBounded) {
  Receipts receipts;
  for (uint64_t stream = 1; stream <= kMaxReceiptStreams; ++stream) {
    ASSERT_EQ(receipts.claim(ReceiptTopic::kPose, sample(0, 0, stream)), Claim::kNew);
  }
  EXPECT_EQ(receipts.claim(ReceiptTopic::kPose, sample(0, 0, kMaxReceiptStreams + 1)),
            Claim::kOutOfWindow);
  EXPECT_EQ(receipts.claim(ReceiptTopic::kPose, sample(1, 0, 5)), Claim::kNew);  // a known one
}

}  // namespace
}  // namespace stereomap::core
