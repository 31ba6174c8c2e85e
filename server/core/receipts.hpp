// What a session has taken of each vehicle's streams, so that a sample re-sent any number of
// times, in any order (a vehicle's spool catching up after an outage, DDS history after a
// restart), is taken exactly once, and what the server acknowledges to the vehicle (AckMsg).
//
// Samples of a stream (nonzero, proto/messages.hpp) are told apart by seq alone: per topic the
// count of seqs taken from 0 with none missing, and the seqs taken above it. A sample's
// unacked_from moves the count past seqs its sender gave up (they never come). Corrections are
// newest-wins: one counts every seq below it as taken. Stream 0 (a sender without streams, and
// journals written before them) keeps the old rule: a sample is new when its seq or its stamp is
// newer than the last taken.
//
//   Receipts receipts;
//   if (receipts.claim(ReceiptTopic::kPose, pose) == Claim::kNew) ...
//   for (const auto& ack : receipts.takeAcks()) writer.write(ack);
//
// Not thread-safe: the session guards it.
#pragma once

#include <array>
#include <cstdint>
#include <map>
#include <set>
#include <string>
#include <tuple>
#include <vector>

#include "proto/messages.hpp"

namespace stereomap::core {

enum class ReceiptTopic { kPose, kCloud, kEvent, kCorrection };
inline constexpr size_t kReceiptTopics = 4;

// A topic's name in metrics ("Pose", ...), and the topic of a message.
const char* receiptTopicName(ReceiptTopic topic);
ReceiptTopic receiptTopicOf(const proto::PoseMsg&);
ReceiptTopic receiptTopicOf(const proto::CloudFrameMsg&);
ReceiptTopic receiptTopicOf(const proto::SessionEventMsg&);
ReceiptTopic receiptTopicOf(const proto::PoseCorrectionMsg&);

// A sample's place in its stream, as the receipts need it.
struct SampleId {
  std::string vehicle;
  uint64_t stream = 0;
  uint64_t seq = 0;
  uint64_t unacked_from = 0;
  int64_t stamp_ns = 0;
  template <typename Message>
  static SampleId of(const Message& m) {
    return {m.vehicle_id, m.stream, m.seq, m.unacked_from, m.stamp_ns};
  }
};

// kOutOfWindow: a stream's seqs taken above its count are bounded (kReceiptWindow), and a
// session's streams (kMaxReceiptStreams: a vehicle starts one per process); a sample that would
// need more is not taken (its sender keeps it and sends it again later).
enum class Claim { kNew, kDuplicate, kOutOfWindow };
inline constexpr size_t kReceiptWindow = 65536;
inline constexpr size_t kMaxReceiptStreams = 16384;

class Receipts {
 public:
  // kNew the first time this sample is seen (and it counts as taken from now on).
  Claim claim(ReceiptTopic topic, const SampleId& sample);
  // What claim() would say, taking nothing. A duplicate of a stream's sample marks its
  // acknowledgement due again: its sender has not heard it.
  Claim check(ReceiptTopic topic, const SampleId& sample);
  // The acknowledgements due (streams whose receipts changed or that sent a duplicate since the
  // last call), session ids left empty; marks them sent.
  std::vector<proto::AckMsg> takeAcks();
  // The acknowledgement of one stream as it stands (zero counts when nothing was taken).
  proto::AckMsg ack(const std::string& vehicle, uint64_t stream) const;
  // Seqs of `topic` that senders gave up (a full spool: passed over by unacked_from without
  // ever arriving) since the last call.
  uint64_t takeGivenUp(ReceiptTopic topic);

 private:
  struct Taken {
    uint64_t contiguous = 0;  // every seq below is taken
    std::set<uint64_t> above;
    // Stream 0: the newest seq and stamp taken (seq 0 and stamp 0 before any).
    uint64_t last_seq = 0;
    int64_t last_stamp = 0;
    bool any = false;
  };
  struct Stream {
    std::array<Taken, kReceiptTopics> topics;
    bool ack_due = false;
  };
  // A new stream beyond kMaxReceiptStreams, or a seq no count can pass.
  bool full(const SampleId& sample) const;
  // The stream's entry with the sample's unacked_from applied.
  Stream& streamOf(const SampleId& sample, ReceiptTopic topic);
  static Claim classify(ReceiptTopic topic, const Taken& taken, const SampleId& sample);
  std::map<std::pair<std::string, uint64_t>, Stream> streams_;  // by (vehicle, stream)
  std::array<uint64_t, kReceiptTopics> given_up_{};
};

}  // namespace stereomap::core
