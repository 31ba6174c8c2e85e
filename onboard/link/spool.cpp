#include "onboard/link/spool.hpp"

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <spdlog/spdlog.h>

#include <algorithm>
#include <charconv>
#include <fstream>
#include <sstream>
#include <system_error>
#include <variant>

#include "common/files.hpp"

namespace stereomap::link {

namespace fs = std::filesystem;
using proto::journal::Journal;

namespace {

constexpr const char* kSegmentPrefix = "spool-";
constexpr const char* kSegmentSuffix = ".smj";
constexpr const char* kAckedName = "acked";
// A failed disk is tried again after this long (a full disk may have room again).
constexpr auto kDiskRetry = std::chrono::seconds(5);

template <typename Message>
const Message* as(const SpoolRecord& record) {
  return std::get_if<Message>(&record);
}

// What a record costs the spool: its payload and fields, about as the journal writes it.
uint64_t recordBytes(const SpoolRecord& record) {
  if (const auto* cloud = as<proto::CloudFrameMsg>(record)) return 160 + cloud->payload.size();
  if (const auto* correction = as<proto::PoseCorrectionMsg>(record)) {
    return 100 + 64 * correction->keyframes.size();
  }
  if (as<proto::PoseMsg>(record) != nullptr) return 420;
  return 140;
}

std::pair<uint64_t, uint64_t> streamAndSeq(const SpoolRecord& record) {
  return std::visit(
      [](const auto& m) {
        return std::pair<uint64_t, uint64_t>{m.stream, m.seq};
      },
      record);
}

const std::string& sessionOf(const SpoolRecord& record) {
  return std::visit([](const auto& m) -> const std::string& { return m.session_id; }, record);
}

// A segment's first record number from its file name, or 0 when it is not one.
uint64_t segmentNumber(const fs::path& path) {
  const std::string name = path.filename().string();
  const std::string prefix = kSegmentPrefix, suffix = kSegmentSuffix;
  if (name.size() <= prefix.size() + suffix.size() || name.rfind(prefix, 0) != 0 ||
      name.compare(name.size() - suffix.size(), suffix.size(), suffix) != 0) {
    return 0;
  }
  const std::string digits =
      name.substr(prefix.size(), name.size() - prefix.size() - suffix.size());
  uint64_t number = 0;
  const auto [end, error] = std::from_chars(digits.data(), digits.data() + digits.size(), number);
  // Digits only, and within 64 bits: any other name is not a segment of ours.
  if (error != std::errc() || end != digits.data() + digits.size() || digits[0] == '+') return 0;
  return number;
}

}  // namespace

SpoolTopic spoolTopicOf(const SpoolRecord& record) {
  if (as<proto::CloudFrameMsg>(record) != nullptr) return SpoolTopic::kCloud;
  if (as<proto::PoseMsg>(record) != nullptr) return SpoolTopic::kPose;
  if (as<proto::PoseCorrectionMsg>(record) != nullptr) return SpoolTopic::kCorrection;
  return SpoolTopic::kEvent;
}

Spool::Spool(const SpoolOptions& options) : options_(options) {}

Spool::~Spool() {
  sync(/*force=*/true);
  writing_.reset();
  if (lock_fd_ >= 0) ::close(lock_fd_);  // and with it the lock
}

common::Result<std::unique_ptr<Spool>> Spool::open(const SpoolOptions& options) {
  using common::ErrorCode;
  if (options.max_bytes == 0 || options.segment_bytes == 0) {
    return common::makeError(ErrorCode::kInvalidArgument, "spool sizes must be positive");
  }
  auto spool = std::unique_ptr<Spool>(new Spool(options));
  if (!options.dir.empty()) {
    std::error_code error;
    fs::create_directories(options.dir, error);
    if (error || !fs::is_directory(options.dir)) {
      return common::makeError(ErrorCode::kIo, "cannot use spool folder " + options.dir.string() +
                                                   ": " +
                                                   (error ? error.message() : "not a folder"));
    }
    // One process per folder: two writing and deleting the same segments would lose samples.
    const fs::path lock = options.dir / "lock";
    spool->lock_fd_ = ::open(lock.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
    if (spool->lock_fd_ < 0) {
      return common::makeError(ErrorCode::kIo, "cannot use spool folder " + options.dir.string() +
                                                   ": " + common::systemError(errno));
    }
    if (::flock(spool->lock_fd_, LOCK_EX | LOCK_NB) != 0) {
      return common::makeError(ErrorCode::kConflict,
                               "spool folder " + options.dir.string() +
                                   " is in use by another vehicle process (give each its own "
                                   "--spool)");
    }
    spool->recover();
  }
  return spool;
}

void Spool::readAcked() {
  std::ifstream in(options_.dir / kAckedName);
  proto::AckMsg ack;
  // Damage costs only resends: a line that does not read is skipped.
  std::string line;
  while (std::getline(in, line)) {
    std::istringstream fields(line);
    if (fields >> ack.stream >> ack.events >> ack.poses >> ack.corrections >> ack.clouds) {
      acked_[ack.stream] = ack;
    }
  }
}

bool Spool::acknowledged(uint64_t stream, SpoolTopic topic, uint64_t seq) const {
  const auto found = acked_.find(stream);
  if (found == acked_.end()) return false;
  const auto& ack = found->second;
  switch (topic) {
    case SpoolTopic::kEvent:
      return seq < ack.events;
    case SpoolTopic::kPose:
      return seq < ack.poses;
    case SpoolTopic::kCorrection:
      return seq < ack.corrections;
    case SpoolTopic::kCloud:
      return seq < ack.clouds;
  }
  return false;
}

void Spool::recover() {
  readAcked();
  std::error_code error;
  std::vector<std::pair<uint64_t, fs::path>> found;
  for (const auto& item : fs::directory_iterator(options_.dir, error)) {
    if (const uint64_t number = segmentNumber(item.path()); number > 0 && item.is_regular_file()) {
      found.emplace_back(number, item.path());
    }
  }
  std::sort(found.begin(), found.end());
  for (const auto& [first, path] : found) {
    auto replay = proto::journal::readJournal(path);
    if (!replay) {
      spdlog::warn("spool: cannot read {}: {}; left as it is", path.string(),
                   replay.error().message);
      continue;
    }
    stats_.lost_records += replay->lostRecords();
    if (!replay->problem.empty()) spdlog::warn("spool: {}: {}", path.string(), replay->problem);
    segments_[first] = {path, 0};
    for (size_t i = 0; i < replay->records.size(); ++i) {
      const uint64_t number = replay->numbers[i];
      auto& record = replay->records[i];
      const auto [stream, seq] = streamAndSeq(record);
      const SpoolTopic topic = spoolTopicOf(record);
      Entry entry{stream, seq, recordBytes(record), 0, first, nullptr};
      entry.record = std::make_shared<SpoolRecord>(std::move(record));
      auto& spooled = spooled_[{stream, topic}];
      spooled = std::max(spooled, seq + 1);
      stream_sessions_[stream] = sessionOf(*entry.record);
      if (acknowledged(stream, topic, seq)) continue;
      if (!by_seq_.try_emplace({stream, topic, seq}, number).second) continue;  // twice in files
      stats_.held_bytes += entry.bytes;
      stats_.memory_bytes += entry.bytes;
      ++segments_[first].held;
      entries_.emplace(Key{topic, number}, std::move(entry));
      ++stats_.recovered;
      next_number_ = std::max(next_number_, number + 1);
      evictFromMemory();
    }
    next_number_ = std::max(next_number_, replay->last_number + 1);
    if (segments_[first].held == 0) release(first);
  }
  stats_.held = entries_.size();
  // Acknowledgements of streams no file holds any more need not be kept.
  std::erase_if(acked_,
                [&](const auto& entry) { return stream_sessions_.count(entry.first) == 0; });
  acked_changed_ = true;
  if (stats_.recovered > 0 || stats_.lost_records > 0) {
    spdlog::info(
        "spool {}: {} samples an earlier run left unacknowledged, to send again ({} "
        "damaged records lost)",
        options_.dir.string(), stats_.recovered, stats_.lost_records);
  }
  makeRoom();
}

void Spool::diskFailed(const std::string& problem) {
  if (stats_.disk_ok) {
    spdlog::error("spool: {}; keeping unacknowledged samples in memory (up to {} MB)", problem,
                  options_.max_bytes >> 20);
  }
  stats_.disk_ok = false;
  stats_.disk_problem = problem;
  writing_.reset();
  if (writing_segment_ != 0) {
    const uint64_t was = writing_segment_;
    writing_segment_ = 0;
    if (segments_.count(was) != 0 && segments_[was].held == 0) release(was);
  }
  disk_failed_at_ = std::chrono::steady_clock::now();
}

void Spool::write(const SpoolRecord& record, Entry& entry, uint64_t number) {
  if (options_.dir.empty()) return;
  const auto now = std::chrono::steady_clock::now();
  if (!stats_.disk_ok && now - disk_failed_at_ < kDiskRetry) return;
  if (!writing_ || writing_->bytes() >= options_.segment_bytes) {
    if (writing_) {
      sync(/*force=*/true);
      writing_.reset();
      const uint64_t was = writing_segment_;
      writing_segment_ = 0;
      if (segments_[was].held == 0) release(was);
    }
    const fs::path path = options_.dir / (kSegmentPrefix + std::to_string(number) + kSegmentSuffix);
    auto opened = Journal::open(path, number);
    if (!opened) return diskFailed(opened.error().message);
    writing_ = std::move(opened).value();
    writing_segment_ = number;
    segments_[number] = {path, 0};
  }
  const uint64_t before = writing_->bytes();
  auto appended = writing_->append(record, Journal::Durability::kLater);
  if (!appended) return diskFailed(appended.error().message);
  if (*appended != number) {
    // The segment numbers on its own (a record it kept from before): start a fresh one.
    return diskFailed("spool segment numbering is out of step");
  }
  if (!stats_.disk_ok) spdlog::info("spool: the disk takes samples again");
  stats_.disk_ok = true;
  stats_.disk_problem.clear();
  stats_.disk_bytes += writing_->bytes() - before;
  entry.segment = writing_segment_;
  ++segments_[writing_segment_].held;
  unsynced_ = true;
}

void Spool::add(SpoolRecord record, int64_t now_ns) {
  const auto [stream, seq] = streamAndSeq(record);
  const SpoolTopic topic = spoolTopicOf(record);
  if (topic == SpoolTopic::kCorrection) {
    // Each correction holds every keyframe: a newer one makes the older ones moot.
    for (auto it = by_seq_.lower_bound({stream, topic, 0}); it != by_seq_.end() &&
                                                            std::get<0>(it->first) == stream &&
                                                            std::get<1>(it->first) == topic;) {
      const uint64_t number = (it++)->second;
      erase(entries_.find({topic, number}));
      ++stats_.superseded;
    }
  }
  const uint64_t number = next_number_++;
  Entry entry{stream, seq, recordBytes(record), now_ns, 0, nullptr};
  write(record, entry, number);
  entry.record = std::make_shared<SpoolRecord>(std::move(record));
  auto& spooled = spooled_[{stream, topic}];
  spooled = std::max(spooled, seq + 1);
  stream_sessions_[stream] = sessionOf(*entry.record);
  by_seq_[{stream, topic, seq}] = number;
  stats_.held_bytes += entry.bytes;
  stats_.memory_bytes += entry.bytes;
  entries_.emplace(Key{topic, number}, std::move(entry));
  ++stats_.added;
  stats_.held = entries_.size();
  makeRoom();
  evictFromMemory();
  sync();
}

void Spool::erase(std::map<Key, Entry>::iterator it) {
  if (it == entries_.end()) return;
  const Entry& entry = it->second;
  by_seq_.erase({entry.stream, it->first.first, entry.seq});
  stats_.held_bytes -= entry.bytes;
  if (entry.record) stats_.memory_bytes -= entry.bytes;
  const uint64_t segment = entry.segment;
  entries_.erase(it);
  stats_.held = entries_.size();
  if (segment != 0 && --segments_[segment].held == 0) release(segment);
}

void Spool::release(uint64_t segment) {
  // The segment being written stays: its records are also what tells a later process how far
  // each stream went (acknowledge()'s check).
  if (segment == writing_segment_) return;
  const auto found = segments_.find(segment);
  if (found == segments_.end()) return;
  std::error_code error;
  fs::remove(found->second.path, error);
  if (segment == cached_segment_) {
    cached_segment_ = 0;
    cached_.clear();
  }
  segments_.erase(found);
}

std::optional<size_t> Spool::acknowledge(const proto::AckMsg& ack) {
  const std::pair<SpoolTopic, uint64_t> counts[] = {{SpoolTopic::kEvent, ack.events},
                                                    {SpoolTopic::kPose, ack.poses},
                                                    {SpoolTopic::kCorrection, ack.corrections},
                                                    {SpoolTopic::kCloud, ack.clouds}};
  const auto session = stream_sessions_.find(ack.stream);
  if (session == stream_sessions_.end() || session->second != ack.session_id) {
    ++stats_.refused_acks;
    return std::nullopt;
  }
  for (const auto& [topic, count] : counts) {
    const auto spooled = spooled_.find({ack.stream, topic});
    if (count > (spooled == spooled_.end() ? 0 : spooled->second)) {
      ++stats_.refused_acks;
      return std::nullopt;
    }
  }
  size_t dropped = 0;
  for (const auto& [topic, count] : counts) {
    const auto end = by_seq_.lower_bound({ack.stream, topic, count});
    for (auto it = by_seq_.lower_bound({ack.stream, topic, 0}); it != end;) {
      const uint64_t number = (it++)->second;
      erase(entries_.find({topic, number}));
      ++dropped;
    }
  }
  stats_.acknowledged += dropped;
  auto& kept = acked_[ack.stream];
  if (dropped > 0 || kept.stream == 0) {
    kept = ack;
    acked_changed_ = true;
  }
  return dropped;
}

size_t Spool::giveUp(const std::string& session) {
  size_t given_up = 0;
  for (const auto& [stream, named] : std::map<uint64_t, std::string>(stream_sessions_)) {
    if (named != session) continue;
    proto::AckMsg all;  // everything ever spooled in the stream
    all.session_id = session;
    all.stream = stream;
    auto count = [&](SpoolTopic topic) {
      const auto spooled = spooled_.find({stream, topic});
      return spooled == spooled_.end() ? uint64_t{0} : spooled->second;
    };
    all.events = count(SpoolTopic::kEvent);
    all.poses = count(SpoolTopic::kPose);
    all.corrections = count(SpoolTopic::kCorrection);
    all.clouds = count(SpoolTopic::kCloud);
    const size_t dropped = acknowledge(all).value_or(0);
    stats_.acknowledged -= dropped;
    given_up += dropped;
  }
  stats_.dropped_closed += given_up;
  return given_up;
}

std::shared_ptr<SpoolRecord> Spool::load(const Entry& entry, uint64_t number) {
  if (entry.record) return entry.record;
  if (entry.segment != cached_segment_ || cached_.count(number) == 0) {
    cached_.clear();
    cached_segment_ = entry.segment;
    const auto segment = segments_.find(entry.segment);
    if (segment == segments_.end()) return nullptr;
    // Records from this one on that are still held and not in memory: the ones sent next.
    auto read = proto::journal::visitJournal(
        segment->second.path, number, [&](SpoolRecord&& record, uint64_t at) {
          const auto held = entries_.find({spoolTopicOf(record), at});
          if (held != entries_.end() && !held->second.record) {
            cached_[at] = std::make_shared<SpoolRecord>(std::move(record));
          }
        });
    if (!read)
      spdlog::warn("spool: cannot read {}: {}", segment->second.path.string(),
                   read.error().message);
  }
  const auto found = cached_.find(number);
  if (found == cached_.end()) return nullptr;
  auto record = found->second;
  cached_.erase(found);
  return record;
}

void Spool::forEachDue(int64_t now_ns, std::chrono::nanoseconds resend_after,
                       const std::function<bool(const SpoolRecord&)>& send) {
  for (auto it = entries_.begin(); it != entries_.end();) {
    Entry& entry = it->second;
    if (now_ns - entry.last_sent_ns < resend_after.count()) {
      ++it;
      continue;
    }
    const auto record = load(entry, it->first.second);
    if (!record) {
      // Damaged on the disk since it was written: it cannot be sent again.
      ++stats_.lost_records;
      erase(it++);
      continue;
    }
    if (!send(*record)) return;
    entry.last_sent_ns = now_ns;
    ++it;
  }
}

std::optional<uint64_t> Spool::lowestHeld(uint64_t stream, SpoolTopic topic) const {
  const auto it = by_seq_.lower_bound({stream, topic, 0});
  if (it == by_seq_.end() || std::get<0>(it->first) != stream || std::get<1>(it->first) != topic) {
    return std::nullopt;
  }
  return std::get<2>(it->first);
}

std::optional<uint64_t> Spool::highestHeld(uint64_t stream, SpoolTopic topic) const {
  auto it = by_seq_.lower_bound({stream, static_cast<SpoolTopic>(static_cast<int>(topic) + 1), 0});
  if (it == by_seq_.begin()) return std::nullopt;
  --it;
  if (std::get<0>(it->first) != stream || std::get<1>(it->first) != topic) return std::nullopt;
  return std::get<2>(it->first);
}

std::vector<uint64_t> Spool::streams() const {
  std::vector<uint64_t> streams;
  for (const auto& [key, count] : spooled_) {
    if (streams.empty() || streams.back() != key.first) streams.push_back(key.first);
  }
  return streams;
}

void Spool::makeRoom() {
  // Oldest clouds first; poses and session events last.
  for (const SpoolTopic topic :
       {SpoolTopic::kCloud, SpoolTopic::kCorrection, SpoolTopic::kPose, SpoolTopic::kEvent}) {
    while (stats_.held_bytes > options_.max_bytes) {
      auto oldest = entries_.lower_bound({topic, 0});
      if (oldest == entries_.end() || oldest->first.first != topic) break;
      ++(topic == SpoolTopic::kCloud ? stats_.dropped_clouds : stats_.dropped_other);
      erase(oldest);
    }
  }
}

void Spool::evictFromMemory() {
  if (stats_.memory_bytes <= options_.memory_bytes) return;
  // Clouds already on the disk, oldest first (they are sent again last).
  for (auto it = entries_.lower_bound({SpoolTopic::kCloud, 0});
       it != entries_.end() && stats_.memory_bytes > options_.memory_bytes; ++it) {
    if (it->second.record && it->second.segment != 0) {
      it->second.record.reset();
      stats_.memory_bytes -= it->second.bytes;
    }
  }
}

void Spool::sync(bool force) {
  if (!unsynced_ && !acked_changed_) return;
  const auto now = std::chrono::steady_clock::now();
  if (!force && now - last_sync_ < options_.sync_every) return;
  last_sync_ = now;
  if (unsynced_ && writing_) {
    unsynced_ = false;
    if (auto synced = writing_->sync(); !synced) diskFailed(synced.error().message);
  }
  if (acked_changed_ && !options_.dir.empty()) {
    acked_changed_ = false;
    // Streams that hold nothing any more need no line: their records are gone or moot.
    std::ostringstream text;
    for (const auto& [stream, ack] : acked_) {
      text << stream << ' ' << ack.events << ' ' << ack.poses << ' ' << ack.corrections << ' '
           << ack.clouds << '\n';
    }
    // A failure costs only resends after a restart: the disk's state is said by write().
    (void)common::writeFileAtomically(options_.dir / kAckedName, text.str());
  }
}

}  // namespace stereomap::link
