#include "server/core/receipts.hpp"

#include <algorithm>
#include <cstdint>
#include <iterator>
#include <utility>

namespace stereomap::core {

const char* receiptTopicName(ReceiptTopic topic) {
  switch (topic) {
    case ReceiptTopic::kPose:
      return "Pose";
    case ReceiptTopic::kCloud:
      return "CloudFrame";
    case ReceiptTopic::kEvent:
      return "SessionEvent";
    case ReceiptTopic::kCorrection:
      return "PoseCorrection";
  }
  return "?";
}

ReceiptTopic receiptTopicOf(const proto::PoseMsg&) { return ReceiptTopic::kPose; }
ReceiptTopic receiptTopicOf(const proto::CloudFrameMsg&) { return ReceiptTopic::kCloud; }
ReceiptTopic receiptTopicOf(const proto::SessionEventMsg&) { return ReceiptTopic::kEvent; }
ReceiptTopic receiptTopicOf(const proto::PoseCorrectionMsg&) { return ReceiptTopic::kCorrection; }

Receipts::Stream& Receipts::streamOf(const SampleId& sample, ReceiptTopic topic) {
  Stream& stream = streams_[{sample.vehicle, sample.stream}];
  if (sample.stream == 0) return stream;
  // What the sender no longer holds is taken or given up; the sample itself it holds.
  Taken& taken = stream.topics[static_cast<size_t>(topic)];
  const uint64_t floor = std::min(sample.unacked_from, sample.seq);
  if (floor > taken.contiguous) {
    const auto passed = taken.above.lower_bound(floor);
    const auto arrived = static_cast<uint64_t>(std::distance(taken.above.begin(), passed));
    if (topic != ReceiptTopic::kCorrection) {
      given_up_[static_cast<size_t>(topic)] += floor - taken.contiguous - arrived;
    }
    taken.contiguous = floor;
    taken.above.erase(taken.above.begin(), passed);
    stream.ack_due = true;
  }
  while (!taken.above.empty() && *taken.above.begin() == taken.contiguous) {
    taken.above.erase(taken.above.begin());
    ++taken.contiguous;
  }
  return stream;
}

Claim Receipts::classify(ReceiptTopic topic, const Taken& taken, const SampleId& sample) {
  if (sample.stream == 0) {
    // Before streams: new when newer in seq or in stamp than the last taken.
    const bool older = sample.seq <= taken.last_seq && sample.stamp_ns <= taken.last_stamp;
    return taken.any && older ? Claim::kDuplicate : Claim::kNew;
  }
  if (sample.seq < taken.contiguous) return Claim::kDuplicate;
  if (topic == ReceiptTopic::kCorrection) return Claim::kNew;  // newest wins
  if (taken.above.count(sample.seq) != 0) return Claim::kDuplicate;
  // The next missing one always closes the gap.
  const bool full = taken.above.size() >= kReceiptWindow && sample.seq != taken.contiguous;
  return full ? Claim::kOutOfWindow : Claim::kNew;
}

bool Receipts::full(const SampleId& sample) const {
  // The last seq could not be counted past (the count would wrap to 0): no sender gets there.
  if (sample.stream != 0 && sample.seq == UINT64_MAX) return true;
  return streams_.size() >= kMaxReceiptStreams &&
         streams_.count({sample.vehicle, sample.stream}) == 0;
}

Claim Receipts::check(ReceiptTopic topic, const SampleId& sample) {
  if (full(sample)) return Claim::kOutOfWindow;
  Stream& stream = streamOf(sample, topic);
  const Claim claim = classify(topic, stream.topics[static_cast<size_t>(topic)], sample);
  if (claim == Claim::kDuplicate && sample.stream != 0) stream.ack_due = true;
  return claim;
}

Claim Receipts::claim(ReceiptTopic topic, const SampleId& sample) {
  if (full(sample)) return Claim::kOutOfWindow;
  Stream& stream = streamOf(sample, topic);
  Taken& taken = stream.topics[static_cast<size_t>(topic)];
  const Claim claim = classify(topic, taken, sample);
  if (sample.stream != 0) stream.ack_due = true;
  if (claim != Claim::kNew) return claim;
  if (sample.stream == 0) {
    taken.any = true;
    taken.last_seq = sample.seq;
    taken.last_stamp = sample.stamp_ns;
  } else if (topic == ReceiptTopic::kCorrection) {
    taken.contiguous = sample.seq + 1;
  } else if (sample.seq == taken.contiguous) {
    ++taken.contiguous;
    while (!taken.above.empty() && *taken.above.begin() == taken.contiguous) {
      taken.above.erase(taken.above.begin());
      ++taken.contiguous;
    }
  } else {
    taken.above.insert(sample.seq);
  }
  return claim;
}

proto::AckMsg Receipts::ack(const std::string& vehicle, uint64_t stream) const {
  proto::AckMsg ack;
  ack.vehicle_id = vehicle;
  ack.stream = stream;
  const auto found = streams_.find({vehicle, stream});
  if (found == streams_.end()) return ack;
  const auto& topics = found->second.topics;
  ack.poses = topics[static_cast<size_t>(ReceiptTopic::kPose)].contiguous;
  ack.clouds = topics[static_cast<size_t>(ReceiptTopic::kCloud)].contiguous;
  ack.events = topics[static_cast<size_t>(ReceiptTopic::kEvent)].contiguous;
  ack.corrections = topics[static_cast<size_t>(ReceiptTopic::kCorrection)].contiguous;
  return ack;
}

uint64_t Receipts::takeGivenUp(ReceiptTopic topic) {
  return std::exchange(given_up_[static_cast<size_t>(topic)], 0);
}

std::vector<proto::AckMsg> Receipts::takeAcks() {
  std::vector<proto::AckMsg> due;
  for (auto& [key, stream] : streams_) {
    if (!stream.ack_due || key.second == 0) continue;
    stream.ack_due = false;
    due.push_back(ack(key.first, key.second));
  }
  return due;
}

}  // namespace stereomap::core
