// What of each vehicle stream reached a session's journal, and what a vehicle's spool folder
// says its streams sent: the outage test's and benchmark's ground truth (issue 38).
#pragma once

#include <cstdint>
#include <filesystem>
#include <map>
#include <set>
#include <string>

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

// The samples in `store`/`session`/journal.smj (empty, with a message on stderr, when it cannot
// be read).
StreamSamples journaledSamples(const std::filesystem::path& store, const std::string& session);

// How far each stream in a spool folder's segments went: one past the highest pose and cloud
// seq in them (the segment being written is never deleted, so its records tell).
struct StreamReach {
  uint64_t poses = 0, clouds = 0;
};
std::map<uint64_t, StreamReach> spooledReach(const std::filesystem::path& spool);

// The number a regular expression's first group matches in `text`, or -1.
double numberIn(const std::string& text, const std::string& pattern);

// A file's text ("" when it cannot be read).
std::string readText(const std::filesystem::path& path);

}  // namespace stereomap::testing
