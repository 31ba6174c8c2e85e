// The vehicle's spool: every sample it sent that the server has not acknowledged yet (poses,
// clouds, session events, pose corrections), so that an outage of any length, or a restart of
// the vehicle's process, loses nothing the server has not journaled (as an MQTT client keeps
// its QoS 1 messages until PUBACK).
//
// Samples are held in memory up to a bound and written to files in the spool's folder as they
// come (proto/journal's format: segments of a few MB, each record checksummed, so that a file
// cut short or damaged by a power loss costs the damaged records, never the spool; flushed to
// the disk every second). A segment is deleted once all its samples are acknowledged; the
// acknowledgements are kept beside them (the file "acked"). A spool opened on a folder holds
// what an earlier process left there unacknowledged (to send again: the server takes each
// sample once, so one acknowledged in the last second before a crash costs only its resend). When
// it is full the oldest clouds go first, poses and session events last. When the disk fails (full,
// read-only) samples stay in memory, and stats() says so.
//
//   auto spool = Spool::open({.dir = "/var/lib/stereomap/spool"});
//   (*spool)->add(pose_msg, now_ns);                  // after sending it
//   (*spool)->acknowledge(ack);                       // drops what the server journaled
//   (*spool)->forEachDue(now_ns, 2s, [&](const SpoolRecord& r) { return resend(r); });
//
// Not thread-safe: the vehicle's frame loop owns it.
#pragma once

#include <chrono>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <tuple>
#include <vector>

#include "common/result.hpp"
#include "proto/journal/journal.hpp"
#include "proto/messages.hpp"

namespace stereomap::link {

using SpoolRecord = proto::journal::JournalRecord;

// The spooled topics, in the order they are sent again: small and vital first.
enum class SpoolTopic : uint8_t { kEvent, kPose, kCorrection, kCloud };
SpoolTopic spoolTopicOf(const SpoolRecord& record);

struct SpoolOptions {
  std::filesystem::path dir;  // empty: memory only (nothing survives the process)
  // Everything held, memory and files (the oldest clouds are given up beyond it). 256 MB
  // hold 3 hours of the default thinned stream (1.4 MB/min), 34 min of a full 1 Mbit/s.
  uint64_t max_bytes = 256ull << 20;
  // Held in memory too (re-sent without reading the disk); older samples are read back from
  // their segment.
  uint64_t memory_bytes = 32ull << 20;
  uint64_t segment_bytes = 4ull << 20;
  std::chrono::milliseconds sync_every{1000};  // how often the files are made durable
};

struct SpoolStats {
  uint64_t held = 0, held_bytes = 0;  // samples not acknowledged yet
  uint64_t memory_bytes = 0;          // of them, in memory
  uint64_t added = 0, acknowledged = 0;
  uint64_t dropped_clouds = 0;  // given up when the spool was full
  uint64_t dropped_other = 0;   // poses, events and corrections given up (it was full of them)
  uint64_t dropped_closed = 0;  // given up because the server closed their session (giveUp)
  uint64_t superseded = 0;      // corrections replaced by a newer one before acknowledged
  uint64_t recovered = 0;       // left by an earlier process, held again
  uint64_t lost_records = 0;    // records an earlier process left damaged
  uint64_t disk_bytes = 0;      // written to the spool's files
  uint64_t refused_acks = 0;    // acknowledgements counting more than was spooled
  bool disk_ok = true;          // false: samples are kept in memory only, see disk_problem
  std::string disk_problem;
};

class Spool {
 public:
  // Opens (creating) the folder and holds every intact record of the segments found in it.
  // A folder that cannot be created or read is an error, and one another process holds is
  // kConflict; damaged records are counted.
  static common::Result<std::unique_ptr<Spool>> open(const SpoolOptions& options);
  ~Spool();
  Spool(const Spool&) = delete;
  Spool& operator=(const Spool&) = delete;

  // Holds a sample that was just sent (its stream and seq are in it), as sent now_ns. A
  // correction replaces the older ones of its stream (each carries every keyframe).
  void add(SpoolRecord record, int64_t now_ns);
  // Drops the samples `ack` covers: those of its stream (any vehicle id: the caller checks it)
  // with a seq below its count for their topic. The number dropped, or nullopt (nothing
  // dropped) when the ack names another session than its stream's samples, or counts more of
  // a topic than were ever spooled in its stream: a forged or confused acknowledgement never
  // costs a sample.
  std::optional<size_t> acknowledge(const proto::AckMsg& ack);
  // Visits the samples sent last at least `resend_after` ago, in SpoolTopic order (oldest
  // first within each); `send` returns false to stop (the link's budget is spent), true when
  // it sent the sample, which then counts as sent now_ns.
  void forEachDue(int64_t now_ns, std::chrono::nanoseconds resend_after,
                  const std::function<bool(const SpoolRecord&)>& send);
  // Gives up every sample held for `session` (the server closed it, and the vehicle was told
  // to drop what it holds): as if acknowledged, so that a later process does not send them
  // again either, and counted in dropped_closed. The number given up.
  size_t giveUp(const std::string& session);
  // The lowest (highest) seq of `topic` held for `stream`, or nullopt when none is.
  std::optional<uint64_t> lowestHeld(uint64_t stream, SpoolTopic topic) const;
  std::optional<uint64_t> highestHeld(uint64_t stream, SpoolTopic topic) const;
  // The streams samples are held for (an earlier process's among them).
  std::vector<uint64_t> streams() const;
  // Makes what was written durable when sync_every has passed (or now with force).
  void sync(bool force = false);

  bool empty() const { return entries_.empty(); }
  const SpoolStats& stats() const { return stats_; }

 private:
  struct Entry {
    uint64_t stream = 0, seq = 0;
    uint64_t bytes = 0;
    int64_t last_sent_ns = 0;
    uint64_t segment = 0;                 // first record number of its segment; 0: none
    std::shared_ptr<SpoolRecord> record;  // null: read back from the segment
  };
  // Entries by (topic, number): the send order.
  using Key = std::pair<SpoolTopic, uint64_t>;
  struct Segment {
    std::filesystem::path path;
    uint64_t held = 0;  // entries still referring to it
  };

  explicit Spool(const SpoolOptions& options);
  void recover();
  void readAcked();
  bool acknowledged(uint64_t stream, SpoolTopic topic, uint64_t seq) const;
  void write(const SpoolRecord& record, Entry& entry, uint64_t number);
  void erase(std::map<Key, Entry>::iterator it);
  void release(uint64_t segment);
  void makeRoom();
  void evictFromMemory();
  std::shared_ptr<SpoolRecord> load(const Entry& entry, uint64_t number);
  void diskFailed(const std::string& problem);

  SpoolOptions options_;
  SpoolStats stats_;
  std::map<Key, Entry> entries_;
  // (stream, topic, seq) -> number, for acknowledgements and lowestHeld().
  std::map<std::tuple<uint64_t, SpoolTopic, uint64_t>, uint64_t> by_seq_;
  uint64_t next_number_ = 1;
  // (stream, topic) -> one past the highest seq ever spooled (held or acknowledged).
  std::map<std::pair<uint64_t, SpoolTopic>, uint64_t> spooled_;
  std::map<uint64_t, std::string> stream_sessions_;  // the session each stream's samples name
  // The newest acknowledgement of each stream, kept in the folder's "acked" file (rewritten at
  // sync() when it changed) so that a later process does not send again what was acknowledged
  // but still sits in a segment.
  std::map<uint64_t, proto::AckMsg> acked_;
  bool acked_changed_ = false;
  std::map<uint64_t, Segment> segments_;  // by first record number
  std::unique_ptr<proto::journal::Journal> writing_;
  uint64_t writing_segment_ = 0;
  bool unsynced_ = false;
  std::chrono::steady_clock::time_point last_sync_, disk_failed_at_;
  // The segment read back last, by record number (re-sending reads them in order).
  uint64_t cached_segment_ = 0;
  std::map<uint64_t, std::shared_ptr<SpoolRecord>> cached_;
  int lock_fd_ = -1;  // flock'd for the spool's lifetime
};

}  // namespace stereomap::link
