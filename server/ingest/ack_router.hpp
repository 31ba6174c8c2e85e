// Acknowledgements to vehicles, each written in its vehicle's own partition
// (proto::vehiclePartition): with DDS Security a vehicle may read there only, so no vehicle
// hears another's acknowledgements, and a closed session's answer reaches only its vehicle.
// One writer per (session, vehicle), made at its first acknowledgement; at most `max_writers`
// (then the least recently used goes, and is made again when needed). One thread's alone.
#pragma once

#include <cstdint>
#include <map>
#include <memory>
#include <string>

#include "common/result.hpp"
#include "proto/dds.hpp"

namespace stereomap::ingest {

class AckRouter {
 public:
  explicit AckRouter(std::shared_ptr<proto::Participant> participant, size_t max_writers = 1024)
      : participant_(std::move(participant)), max_writers_(max_writers) {}
  common::Status send(const proto::AckMsg& ack);
  size_t writers() const { return writers_.size(); }

 private:
  struct Entry {
    std::unique_ptr<proto::Writer<proto::AckMsg>> writer;
    uint64_t used = 0;
  };
  std::shared_ptr<proto::Participant> participant_;
  size_t max_writers_;
  std::map<std::string, Entry> writers_;  // by partition
  uint64_t clock_ = 0;
};

}  // namespace stereomap::ingest
