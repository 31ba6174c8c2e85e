// Test samples written as vehicles write them: each in its own vehicle's DDS partition
// (proto::vehiclePartition of its session and vehicle id), on a writer made for that partition
// the first time and matched with the server's reader before the first sample, since the
// server takes a sample only from its own vehicle's partition. Hostile ids get a partition of
// their own too: the server's validation, not the partition, is what such a test tries.
#pragma once

#include <chrono>
#include <map>
#include <memory>
#include <string>

#include "common/result.hpp"
#include "proto/dds.hpp"

namespace stereomap::testing {

template <typename T>
class VehicleWriters {
 public:
  explicit VehicleWriters(std::shared_ptr<proto::Participant> participant)
      : participant_(std::move(participant)) {}

  common::Status write(const T& sample) {
    const std::string partition = proto::vehiclePartition(sample.session_id, sample.vehicle_id);
    auto found = writers_.find(partition);
    if (found == writers_.end()) {
      auto writer = proto::Writer<T>::create(participant_, {partition});
      if (!writer) return writer.error();
      if (!(*writer)->waitForReaders(1, std::chrono::seconds(20))) {
        return common::makeError(common::ErrorCode::kUnavailable,
                                 "no server reads partition " + partition);
      }
      found = writers_.emplace(partition, std::move(writer).value()).first;
    }
    return found->second->write(sample);
  }

 private:
  std::shared_ptr<proto::Participant> participant_;
  std::map<std::string, std::unique_ptr<proto::Writer<T>>> writers_;
};

}  // namespace stereomap::testing
