// What of each vehicle stream reached a session's journal, and what a vehicle's spool folder
// says its streams sent: the outage test's and benchmark's ground truth (issue 38).
#pragma once

#include <cstdint>
#include <filesystem>
#include <map>
#include <set>
#include <string>
#include <vector>

#include "proto/journal/journal.hpp"

namespace stereomap::testing {

// Distinct seqs by stream, per topic, and the records that repeated one (a sample taken twice).
struct StreamSamples {
  std::map<uint64_t, std::set<uint64_t>> poses, clouds;
  size_t repeated = 0;
  size_t poseCount() const;
  size_t cloudCount() const;
  // Of `stream`: the seqs journaled (0 when none).
  size_t poseCount(uint64_t stream) const;
  size_t cloudCount(uint64_t stream) const;
};

// The samples among journal records (a cluster's journal, read from its database).
StreamSamples samplesIn(const std::vector<proto::journal::JournalRecord>& records);

// The samples in `store`/`session`/journal.smj (empty, with a message on stderr, when it cannot
// be read).
StreamSamples journaledSamples(const std::filesystem::path& store, const std::string& session);

// How far each stream in a spool folder's segments went: one past the highest pose and cloud
// seq in them (the segment being written is never deleted, so its records tell).
struct StreamReach {
  uint64_t poses = 0, clouds = 0;
};
std::map<uint64_t, StreamReach> spooledReach(const std::filesystem::path& spool);

// The vehicle as users fly it (thinned clouds, a 1 Mbit/s budget, its spool in `spool`:
// memory or a folder), with ground-truth poses (the odometry is not what is tested), at
// 10 Hz, on `domain`; `extra` flags override these.
std::vector<std::string> userVehicleArgs(int domain, const std::string& session, int frames,
                                         const std::string& spool,
                                         const std::vector<std::string>& extra = {});

// What a vehicle says it sent, from its log's closing lines.
struct Sent {
  size_t poses = 0, clouds = 0;
};
Sent sentBy(const std::string& log);

// The number a regular expression's first group matches in `text`, or -1.
double numberIn(const std::string& text, const std::string& pattern);

// A file's text ("" when it cannot be read).
std::string readText(const std::filesystem::path& path);

}  // namespace stereomap::testing
