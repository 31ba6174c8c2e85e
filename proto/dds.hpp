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
  // DDS Security: a folder made by stereomap-certs for this participant's identity
  // (identity_ca.pem, identity.pem, identity.key, permissions_ca.pem, governance.p7s,
  // permissions.p7s, and crl.pem when present). Empty: no security (the loopback config).
  std::string security_dir;
};

// The files a security folder must hold (see DdsOptions::security_dir), checked before Cyclone
// sees them so a missing file is named.
common::Status checkSecurityDir(const std::string& dir);
// What in a security folder runs out within `ahead` or has run out: its certificate's end, its
// CRL's next update (past it, every handshake fails). One sentence each, for the binary to log
// at start (a warning ahead, an error once past); empty when nothing is due.
std::vector<std::string> securityDatesDue(const std::string& dir, std::chrono::hours ahead);
// Cyclone 0.10.2's governance and permissions parsers take domain ids up to 230.
inline constexpr uint32_t kMaxSecureDomain = 230;

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

// DDS partitions route a session's samples and carry who sent them: vehicle V writes (and
// reads its acknowledgements) in "sm/<session>/v/V" only; a single server reads every one
// ("sm/*"); in a cluster only a session's owner reads "sm/<session>/v/*" (docs/PROTOCOL.md,
// "Partitions"). Ids cannot hold '/', '*' or '?' (core::isValidId), so the partition names
// its session and vehicle unambiguously and is never a wildcard. With DDS Security a
// vehicle's signed permissions allow it only its own partitions: a sample's partition is then
// its writer's proven identity, and a reader made with `bind_to_writer` refuses a sample whose
// vehicle_id is not the one its writer's partition names.
std::string vehiclePartition(const std::string& session_id, const std::string& vehicle_id);
std::string sessionPartitions(const std::string& session_id);  // every vehicle of a session
inline constexpr const char* kEverySessionPartition = "sm/*";

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
  // "bad_enum" (a value out of range) or "identity" (written by a writer whose partition names
  // another vehicle or session, or none: see vehiclePartition).
  std::string reason = "bad_enum";
  std::string writer_partition;  // for "identity": the partition(s) its writer wrote in
};

template <typename T>
class Reader {
 public:
  // In `partitions` (none: the default partition); a name may be a wildcard ("sm/*").
  // `bind_to_writer`: a sample is taken only when its writer wrote in exactly
  // vehiclePartition(sample.session_id, sample.vehicle_id); the rest go to `refused`.
  static common::Result<std::unique_ptr<Reader>> create(
      const std::shared_ptr<Participant>& participant,
      const std::vector<std::string>& partitions = {}, bool bind_to_writer = false);
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
