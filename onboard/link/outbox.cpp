#include "onboard/link/outbox.hpp"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <random>
#include <variant>

#include "proto/wire_size.hpp"

namespace stereomap::link {

namespace {
// Samples sent again get the link's rate less a tenth (DDS's own heartbeats, acknowledgements
// and retransmissions), and save up at most this much of it (no burst that delays live poses).
constexpr double kResendShare = 0.9;
constexpr double kMaxSavedSeconds = 0.25;
}  // namespace

uint64_t randomStreamId() {
  std::random_device device;
  uint64_t id = 0;
  while (id == 0) id = (static_cast<uint64_t>(device()) << 32) ^ device();
  return id;
}

Outbox::Outbox(std::unique_ptr<Spool> spool, const OutboxOptions& options, Send send)
    : spool_(std::move(spool)), options_(options), send_(std::move(send)) {
  if (options_.stream == 0) options_.stream = randomStreamId();
}

template <typename Message>
common::Status Outbox::sendLive(Message& message, SpoolTopic topic, int64_t now_ns) {
  uint64_t& next = next_seq_[static_cast<size_t>(topic)];
  message.stream = options_.stream;
  message.seq = next++;
  message.unacked_from = spool_->lowestHeld(options_.stream, topic).value_or(message.seq);
  if (closed_) {
    ++stats_.held_back;
    if (options_.keep_when_closed) spool_->add(message, now_ns);
    return common::Ok{};
  }
  auto status = send_(message);
  if (status) {
    ++stats_.sent;
  } else {
    ++stats_.send_errors;
  }
  charge(proto::wireBytes(message), now_ns);
  spool_->add(message, now_ns);  // kept whether or not DDS took it
  return status;
}

common::Status Outbox::send(proto::PoseMsg& pose, int64_t now_ns) {
  return sendLive(pose, SpoolTopic::kPose, now_ns);
}
common::Status Outbox::send(proto::CloudFrameMsg& cloud, int64_t now_ns) {
  return sendLive(cloud, SpoolTopic::kCloud, now_ns);
}
common::Status Outbox::send(proto::SessionEventMsg& event, int64_t now_ns) {
  return sendLive(event, SpoolTopic::kEvent, now_ns);
}
common::Status Outbox::send(proto::PoseCorrectionMsg& correction, int64_t now_ns) {
  return sendLive(correction, SpoolTopic::kCorrection, now_ns);
}

void Outbox::refill(int64_t now_ns) {
  const double rate = options_.link_bits_per_s / 8 * kResendShare;
  if (refilled_ns_) tokens_ += rate * static_cast<double>(now_ns - *refilled_ns_) * 1e-9;
  tokens_ = std::clamp(tokens_, -rate, rate * kMaxSavedSeconds);
  refilled_ns_ = now_ns;
}

void Outbox::charge(uint64_t bytes, int64_t now_ns) {
  if (options_.link_bits_per_s <= 0) return;
  refill(now_ns);
  tokens_ -= static_cast<double>(bytes);
}

void Outbox::acknowledge(const proto::AckMsg& ack) {
  if (ack.vehicle_id != options_.vehicle_id) {
    ++stats_.foreign_acks;
    return;
  }
  if (ack.status != proto::AckStatus::kJournaled) return;  // counts nothing (closeSession)
  if (spool_->acknowledge(ack)) ++stats_.acks;
}

void Outbox::watchServer(int64_t now_ns, bool server_present) {
  if (server_was_present_ && !server_present) {
    server_left_ns_ = now_ns;
    spdlog::warn("link: the server has gone; keeping what it has not acknowledged ({} samples)",
                 spool_->stats().held);
  } else if (!server_was_present_ && server_present && server_left_ns_) {
    ++stats_.outages;
    returned_ns_ = now_ns;
    resent_at_return_ = stats_.resent;
    backlog_.clear();
    for (const uint64_t stream : spool_->streams()) {
      for (const SpoolTopic topic :
           {SpoolTopic::kEvent, SpoolTopic::kPose, SpoolTopic::kCorrection, SpoolTopic::kCloud}) {
        if (auto highest = spool_->highestHeld(stream, topic)) backlog_[{stream, topic}] = *highest;
      }
    }
    spdlog::info("link: the server is back after {:.1f} s; {} samples to send again",
                 static_cast<double>(now_ns - *server_left_ns_) * 1e-9, spool_->stats().held);
  }
  server_was_present_ = server_present;
  if (!returned_ns_) return;
  for (const auto& [key, highest] : backlog_) {
    const auto lowest = spool_->lowestHeld(key.first, key.second);
    if (lowest && *lowest <= highest) return;
  }
  stats_.last_catch_up_s = static_cast<double>(now_ns - *returned_ns_) * 1e-9;
  spdlog::info("link: caught up {:.1f} s after the server came back ({} samples sent again)",
               stats_.last_catch_up_s, stats_.resent - resent_at_return_);
  returned_ns_.reset();
}

size_t Outbox::closeSession(const std::string& session) {
  closed_ = true;
  if (options_.keep_when_closed) return 0;
  const size_t given_up = spool_->giveUp(session);
  spool_->sync(/*force=*/true);  // given up for good, even if the process is killed next
  return given_up;
}

void Outbox::resend(int64_t now_ns, bool server_present) {
  if (closed_) return;
  watchServer(now_ns, server_present);
  if (!server_present || spool_->empty()) return;
  const bool budgeted = options_.link_bits_per_s > 0;
  if (budgeted) refill(now_ns);
  spool_->forEachDue(now_ns, options_.resend_after, [&](const SpoolRecord& held) {
    return std::visit(
        [&](const auto& message) {
          const uint64_t bytes = proto::wireBytes(message);
          if (budgeted && tokens_ < static_cast<double>(bytes)) return false;
          auto copy = message;
          // What the spool holds now: the server may pass what was given up since.
          copy.unacked_from =
              spool_->lowestHeld(copy.stream, spoolTopicOf(held)).value_or(copy.seq);
          if (!send_(copy)) {
            ++stats_.send_errors;
            return false;
          }
          tokens_ -= static_cast<double>(bytes);
          ++stats_.resent;
          stats_.resent_bytes += bytes;
          return true;
        },
        held);
  });
}

}  // namespace stereomap::link
