// RAII wrappers over Cyclone DDS's C API for stereomap's topics: a Participant on a
// domain (configured from an XML file, never multicast by default), typed Writers and
// Readers whose take() waits on a WaitSet (no sleep-polling) and can be woken for shutdown.
// Cyclone's return codes become common::Error values; nothing of Cyclone leaks out.
//
//   auto participant = Participant::create({.domain_id = 7, .config_file = "cfg.xml"});
//   auto writer = Writer<PoseMsg>::create(*participant);
//   writer->write(pose);
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "common/result.hpp"
#include "proto/messages.hpp"

namespace stereomap::proto {

struct DdsOptions {
  uint32_t domain_id = 0;
  // Cyclone XML configuration file. Empty: $CYCLONEDDS_URI if set, else the built-in
  // loopback-only configuration (unicast on 127.0.0.1), so nothing leaves the host by accident.
  std::string config_file;
};

class Participant {
 public:
  static common::Result<std::shared_ptr<Participant>> create(const DdsOptions& options);
  ~Participant();
  Participant(const Participant&) = delete;
  Participant& operator=(const Participant&) = delete;

  int32_t handle() const;  // dds_entity_t, for the typed wrappers in proto only

 private:
  struct Impl;
  explicit Participant(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// DDS partitions route a session's samples: a vehicle writes (and reads its acknowledgements)
// in its session's partition, "sm.<session>"; a single server reads every one ("sm.*", and
// the default partition "" for writers that name none); in a cluster only a session's owner
// reads its partition (docs/PROTOCOL.md, "Partitions"). Session ids cannot hold '*' or '?'
// (core::isValidId), so no id is a wildcard.
std::string sessionPartition(const std::string& session_id);
inline constexpr const char* kEverySessionPartition = "sm.*";
// What a single server reads and writes in: every session's partition and the default one.
std::vector<std::string> everyPartition();

// One writer of topic T (a message of messages.hpp) with T's QoS preset, in `partitions`
// (none: the default partition).
template <typename T>
class Writer {
 public:
  static common::Result<std::unique_ptr<Writer>> create(
      const std::shared_ptr<Participant>& participant,
      const std::vector<std::string>& partitions = {});
  ~Writer();
  // Copies `message` into a DDS sample and writes it; fails (without throwing) on a bound
  // violation or a DDS error.
  common::Status write(const T& message);
  // Number of matched readers (for waiting on discovery before the first sample).
  int matchedReaders() const;
  // Waits until at least `count` readers matched or `timeout` passed; true if matched.
  bool waitForReaders(int count, std::chrono::milliseconds timeout) const;
  // Waits until every matched reader acknowledged every sample written (at once when none is
  // matched) or `timeout` passed; true when all were.
  bool waitForAcks(std::chrono::milliseconds timeout) const;

 private:
  struct Impl;
  explicit Writer(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// One reader of topic T with T's QoS preset.
// A received sample that its type's checks refused (an enumeration's value out of range):
// its IDL type ("Pose", "CloudFrame", ...), who sent it as far as its ids say, and what was
// wrong.
struct RefusedSample {
  std::string type;
  std::string vehicle_id;
  std::string session_id;
  std::string detail;
};

template <typename T>
class Reader {
 public:
  // In `partitions` (none: the default partition); a name may be a wildcard ("sm.*").
  static common::Result<std::unique_ptr<Reader>> create(
      const std::shared_ptr<Participant>& participant,
      const std::vector<std::string>& partitions = {});
  ~Reader();
  // Waits up to `timeout` for samples (or wake()), then appends every available valid sample
  // to `out`, and each one refused by its type's checks to `refused` when given. Returns the
  // number appended. Thread-safe against wake() only.
  size_t take(std::vector<T>& out, std::chrono::milliseconds timeout,
              std::vector<RefusedSample>* refused = nullptr);
  // Makes a blocked take() return now (for shutdown). Callable from any thread.
  void wake();
  int matchedWriters() const;

 private:
  struct Impl;
  explicit Reader(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// The built-in loopback-only configuration (also in config/cyclonedds-loopback.xml).
const char* loopbackConfigXml();

}  // namespace stereomap::proto
