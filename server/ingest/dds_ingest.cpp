#include "server/ingest/dds_ingest.hpp"

#include <spdlog/spdlog.h>

namespace stereomap::ingest {

namespace {

template <typename T>
common::Status open(const std::shared_ptr<proto::Participant>& participant,
                    const std::vector<std::string>& partitions,
                    std::unique_ptr<proto::Reader<T>>& reader) {
  auto created = proto::Reader<T>::create(participant, partitions, /*bind_to_writer=*/true);
  if (!created) {
    return common::makeError(created.error().code,
                             "cannot create DDS readers: " + created.error().message);
  }
  reader = std::move(created).value();
  return common::Ok{};
}

}  // namespace

common::Result<std::unique_ptr<DdsIngest>> DdsIngest::create(
    const std::shared_ptr<proto::Participant>& participant,
    const std::vector<std::string>& partitions, bool events) {
  auto ingest = std::unique_ptr<DdsIngest>(new DdsIngest);
  auto& [clouds, poses, corrections, landing, vehicle_status, session_events] = ingest->readers_;
  for (auto status :
       {open(participant, partitions, clouds), open(participant, partitions, poses),
        open(participant, partitions, corrections), open(participant, partitions, landing),
        open(participant, partitions, vehicle_status)}) {
    if (!status) return status.error();
  }
  if (events) {
    if (auto status = open(participant, partitions, session_events); !status) {
      return status.error();
    }
  }
  return ingest;
}

DdsIngest::~DdsIngest() {
  stop();
  join();
}

void DdsIngest::start(core::MapServer& server) {
  std::apply(
      [&](auto&... readers) {
        auto launch = [&](auto& reader) {
          if (reader)
            threads_.emplace_back([this, &server, r = reader.get()] { pump(*r, server); });
        };
        (launch(readers), ...);
      },
      readers_);
}

void DdsIngest::stop() {
  stopping_ = true;
  std::apply(
      [](auto&... readers) {
        auto wake = [](auto& reader) {
          if (reader) reader->wake();
        };
        (wake(readers), ...);
      },
      readers_);
}

void DdsIngest::join() {
  for (auto& thread : threads_) thread.join();
  threads_.clear();
}

template <typename T>
void DdsIngest::pump(proto::Reader<T>& reader, core::MapServer& server) {
  std::vector<T> batch;
  std::vector<proto::RefusedSample> refused;
  bool last_round = false;
  while (!last_round) {
    last_round = stopping_;  // after a stop: one more round for what arrived
    batch.clear();
    refused.clear();
    reader.take(batch, last_round ? std::chrono::milliseconds(0) : std::chrono::milliseconds(500),
                &refused);
    for (const auto& sample : refused) server.refuse(sample);
    for (const auto& sample : batch) server.ingest(sample);
  }
}

void sendAcksUntil(core::MapServer& server, const AckSend& send,
                   const std::function<bool(std::chrono::milliseconds)>& stopped) {
  do {
    for (const auto& ack : server.takeAcks()) {
      if (auto written = send(ack); !written) {
        spdlog::warn("cannot send an acknowledgement to '{}': {}", ack.vehicle_id,
                     written.error().message);
      }
    }
  } while (!stopped(kAckPeriod));
}

}  // namespace stereomap::ingest
