#include "tests/support/stream_count.hpp"

#include <algorithm>
#include <cstdio>
#include <fstream>
#include <regex>
#include <sstream>
#include <variant>

#include "proto/journal/journal.hpp"
#include "tests/support/server_fixture.hpp"

namespace stereomap::testing {

namespace {
size_t total(const std::map<uint64_t, std::set<uint64_t>>& by_stream) {
  size_t n = 0;
  for (const auto& [stream, seqs] : by_stream) n += seqs.size();
  return n;
}
size_t ofStream(const std::map<uint64_t, std::set<uint64_t>>& by_stream, uint64_t stream) {
  const auto found = by_stream.find(stream);
  return found == by_stream.end() ? 0 : found->second.size();
}
}  // namespace

size_t StreamSamples::poseCount() const { return total(poses); }
size_t StreamSamples::cloudCount() const { return total(clouds); }
size_t StreamSamples::poseCount(uint64_t stream) const { return ofStream(poses, stream); }
size_t StreamSamples::cloudCount(uint64_t stream) const { return ofStream(clouds, stream); }

StreamSamples samplesIn(const std::vector<proto::journal::JournalRecord>& records) {
  StreamSamples out;
  for (const auto& record : records) {
    if (const auto* pose = std::get_if<proto::PoseMsg>(&record)) {
      out.repeated += !out.poses[pose->stream].insert(pose->seq).second;
    } else if (const auto* cloud = std::get_if<proto::CloudFrameMsg>(&record)) {
      out.repeated += !out.clouds[cloud->stream].insert(cloud->seq).second;
    }
  }
  return out;
}

StreamSamples journaledSamples(const std::filesystem::path& store, const std::string& session) {
  auto replay = proto::journal::readJournal(store / session / "journal.smj");
  if (!replay) {
    std::fprintf(stderr, "cannot read the journal: %s\n", replay.error().message.c_str());
    return {};
  }
  return samplesIn(replay->records);
}

std::map<uint64_t, StreamReach> spooledReach(const std::filesystem::path& spool) {
  std::map<uint64_t, StreamReach> reach;
  std::error_code error;
  for (const auto& item : std::filesystem::directory_iterator(spool, error)) {
    if (item.path().extension() != ".smj") continue;
    auto replay = proto::journal::readJournal(item.path());
    if (!replay) continue;
    for (const auto& record : replay->records) {
      if (const auto* pose = std::get_if<proto::PoseMsg>(&record)) {
        auto& r = reach[pose->stream];
        r.poses = std::max(r.poses, pose->seq + 1);
      } else if (const auto* cloud = std::get_if<proto::CloudFrameMsg>(&record)) {
        auto& r = reach[cloud->stream];
        r.clouds = std::max(r.clouds, cloud->seq + 1);
      }
    }
  }
  return reach;
}

std::vector<std::string> userVehicleArgs(int domain, const std::string& session, int frames,
                                         const std::string& spool,
                                         const std::vector<std::string>& extra) {
  std::vector<std::string> args = extra;
  const std::pair<std::string, std::string> defaults[] = {
      {"--rate", "10"},           {"--vo", "gt"},
      {"--min-new", "0.1"},       {"--map-resolution", "0.1"},
      {"--link-budget", "1Mbit"}, {"--spool", spool},
      {"--flush-timeout", "60"}};
  for (const auto& [flag, value] : defaults) {
    if (std::find(extra.begin(), extra.end(), flag) == extra.end()) {
      args.insert(args.end(), {flag, value});
    }
  }
  return onboardArgs(domain, session, frames, args);
}

Sent sentBy(const std::string& log) {
  return {static_cast<size_t>(numberIn(log, R"(done: ([0-9]+) frames)")),
          static_cast<size_t>(
              numberIn(log, R"(link: sent [0-9]+ kbit/s \(clouds and poses\), ([0-9]+) of)"))};
}

double numberIn(const std::string& text, const std::string& pattern) {
  std::smatch match;
  if (!std::regex_search(text, match, std::regex(pattern))) return -1;
  return std::stod(match[1].str());
}

std::string readText(const std::filesystem::path& path) {
  std::ifstream in(path);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

}  // namespace stereomap::testing
