#include "server/ingest/ack_router.hpp"

#include <algorithm>
#include <chrono>

namespace stereomap::ingest {

common::Status AckRouter::send(const proto::AckMsg& ack) {
  const std::string partition = proto::vehiclePartition(ack.session_id, ack.vehicle_id);
  auto found = writers_.find(partition);
  if (found == writers_.end()) {
    if (writers_.size() >= max_writers_) {
      writers_.erase(std::min_element(writers_.begin(), writers_.end(), [](auto& a, auto& b) {
        return a.second.used < b.second.used;
      }));
    }
    auto writer = proto::Writer<proto::AckMsg>::create(participant_, {partition});
    if (!writer) return writer.error();
    // The vehicle's reader is known already (it sent what this acknowledges): matching is
    // local, but a sample written before it would reach no one, so wait for it briefly.
    (*writer)->waitForReaders(1, std::chrono::milliseconds(100));
    found = writers_.emplace(partition, Entry{std::move(writer).value(), 0}).first;
  }
  found->second.used = ++clock_;
  return found->second.writer->write(ack);
}

}  // namespace stereomap::ingest
