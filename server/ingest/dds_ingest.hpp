// DDS to the MapServer: a reader per topic in given partitions and a thread per reader
// handing its samples to the server, and the loop that sends the server's acknowledgements.
// The single server reads every partition for its whole life; a cluster server (server/
// cluster) reads each session it owns in that session's partition, from when it takes the
// session until it loses it.
#pragma once

#include <atomic>
#include <chrono>
#include <functional>
#include <memory>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include "common/result.hpp"
#include "proto/dds.hpp"
#include "server/core/map_server.hpp"

namespace stereomap::ingest {

class DdsIngest {
 public:
  // Readers of clouds, poses, corrections, landing targets and vehicles' status, and of
  // session events when `events`, in `partitions`.
  static common::Result<std::unique_ptr<DdsIngest>> create(
      const std::shared_ptr<proto::Participant>& participant,
      const std::vector<std::string>& partitions, bool events);
  ~DdsIngest();  // stop() and join()
  DdsIngest(const DdsIngest&) = delete;
  DdsIngest& operator=(const DdsIngest&) = delete;

  void start(core::MapServer& server);
  // Makes every reader's thread take one more round of what has arrived and end. Any thread.
  void stop();
  void join();

 private:
  DdsIngest() = default;
  template <typename T>
  void pump(proto::Reader<T>& reader, core::MapServer& server);

  std::tuple<std::unique_ptr<proto::Reader<proto::CloudFrameMsg>>,
             std::unique_ptr<proto::Reader<proto::PoseMsg>>,
             std::unique_ptr<proto::Reader<proto::PoseCorrectionMsg>>,
             std::unique_ptr<proto::Reader<proto::LandingTargetMsg>>,
             std::unique_ptr<proto::Reader<proto::VehicleStatusMsg>>,
             std::unique_ptr<proto::Reader<proto::SessionEventMsg>>>
      readers_;
  std::atomic<bool> stopping_{false};
  std::vector<std::thread> threads_;
};

// Writes one acknowledgement where its session's vehicles read them; fails (said, not
// retried: the next one carries as much) when it cannot.
using AckSend = std::function<common::Status(const proto::AckMsg& ack)>;

// Sends what the server has journaled (MapServer::takeAcks) every kAckPeriod through `send`,
// until `stopped` returns true (it waits the period).
inline constexpr std::chrono::milliseconds kAckPeriod{200};
void sendAcksUntil(core::MapServer& server, const AckSend& send,
                   const std::function<bool(std::chrono::milliseconds)>& stopped);

}  // namespace stereomap::ingest
