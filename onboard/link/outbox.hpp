// Sending so that the server gets every sample: the vehicle's end of the acknowledgements
// (proto/messages.hpp, AckMsg). Each sample is numbered in the vehicle's stream (a random id
// per process, as a Kafka producer's), sent, and kept in the spool (spool.hpp) until the
// server says it is journaled; what is not acknowledged within resend_after is sent again once
// a server is there, after the live samples and within the link's budget, so that catching up
// never delays live poses: session events and poses first, then corrections, then clouds,
// oldest first. A spool an earlier process left is sent again the same way (its samples keep
// their stream, which the server acknowledges apart).
//
//   Outbox outbox(std::move(spool), {.vehicle_id = "uav-1", .link_bits_per_s = 1e6}, send);
//   outbox.send(pose);                        // numbers, sends, keeps
//   outbox.acknowledge(ack);                  // from the Ack topic
//   outbox.resend(now_ns, server_present);    // once a frame
//
// Not thread-safe: the vehicle's frame loop owns it.
#pragma once

#include <array>
#include <chrono>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>

#include "common/result.hpp"
#include "onboard/link/spool.hpp"
#include "proto/messages.hpp"

namespace stereomap::link {

struct OutboxOptions {
  std::string vehicle_id;
  // The whole link's rate (--link-budget): live samples always go; samples sent again use
  // what they leave of it (less a tenth for DDS's own traffic). 0: sent again without a budget.
  double link_bits_per_s = 0;
  // A sample not acknowledged this long after it was sent is sent again (acknowledgements
  // come a few times a second; DDS retransmits on its own within an outage of a few seconds).
  std::chrono::milliseconds resend_after{3000};
  uint64_t stream = 0;  // 0: a random one
  // When the server says the session is closed (closeSession): keep what is held, and what
  // the vehicle makes after, in the spool (true, --on-closed keep), or give it up.
  bool keep_when_closed = true;
};

struct OutboxStats {
  uint64_t sent = 0;           // live samples
  uint64_t resent = 0;         // samples sent again
  uint64_t resent_bytes = 0;   // on the link (proto/wire_size.hpp)
  uint64_t acks = 0;           // acknowledgements taken
  uint64_t foreign_acks = 0;   // for another vehicle: ignored
  uint64_t send_errors = 0;    // DDS refused a write (the sample stays in the spool)
  uint64_t outages = 0;        // times the server went away and came back
  double last_catch_up_s = 0;  // from its return to everything held then acknowledged
  uint64_t held_back = 0;      // live samples not sent: the server closed the session
};

class Outbox {
 public:
  // Writes one sample to DDS (the vehicle's writers); an error keeps it in the spool.
  using Send = std::function<common::Status(const SpoolRecord&)>;
  Outbox(std::unique_ptr<Spool> spool, const OutboxOptions& options, Send send);

  // Numbers a live sample in the stream (stream, seq, unacked_from), sends it and keeps it
  // until acknowledged; `now_ns` is the steady time of sending. The send's status.
  common::Status send(proto::PoseMsg& pose, int64_t now_ns);
  common::Status send(proto::CloudFrameMsg& cloud, int64_t now_ns);
  common::Status send(proto::SessionEventMsg& event, int64_t now_ns);
  common::Status send(proto::PoseCorrectionMsg& correction, int64_t now_ns);
  // Other live traffic on the link (landing targets), for the budget.
  void charge(uint64_t bytes, int64_t now_ns);

  // Takes an acknowledgement: its vehicle must be ours (the spool checks stream and counts).
  void acknowledge(const proto::AckMsg& ack);
  // Sends again what is due, within the budget; nothing without a server to send to, nor once
  // the session is closed.
  void resend(int64_t now_ns, bool server_present);
  // The server closed `session` (AckStatus::kSessionClosed): nothing more is sent, live or
  // again; live samples are still numbered and, with keep_when_closed, kept in the spool with
  // what it holds, else given up with it (Spool::giveUp). The number given up.
  size_t closeSession(const std::string& session);
  bool closed() const { return closed_; }

  uint64_t stream() const { return options_.stream; }
  const OutboxOptions& options() const { return options_; }
  bool caughtUp() const { return spool_->empty(); }
  const Spool& spool() const { return *spool_; }
  Spool& spool() { return *spool_; }
  const OutboxStats& stats() const { return stats_; }

 private:
  template <typename Message>
  common::Status sendLive(Message& message, SpoolTopic topic, int64_t now_ns);
  void refill(int64_t now_ns);
  // The server's comings and goings, and the catching up after each return.
  void watchServer(int64_t now_ns, bool server_present);

  std::unique_ptr<Spool> spool_;
  OutboxOptions options_;
  Send send_;
  OutboxStats stats_;
  std::array<uint64_t, 4> next_seq_{};  // by SpoolTopic
  // The budget's token bucket, bytes (negative: live traffic overdrew it), and its last refill.
  double tokens_ = 0;
  std::optional<int64_t> refilled_ns_;
  bool server_was_present_ = false;
  bool closed_ = false;
  std::optional<int64_t> server_left_ns_;
  // After a return: when, and the highest seq held then per (stream, topic): caught up once
  // none of those is held.
  std::optional<int64_t> returned_ns_;
  std::map<std::pair<uint64_t, SpoolTopic>, uint64_t> backlog_;
  uint64_t resent_at_return_ = 0;
};

// A random nonzero stream id.
uint64_t randomStreamId();

}  // namespace stereomap::link
