#include "proto/journal/journal.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cstring>
#include <optional>

#include "common/files.hpp"

namespace stereomap::proto::journal {

namespace fs = std::filesystem;
using common::ErrorCode;
using common::makeError;

namespace {

constexpr char kMagicV1[8] = {'S', 'M', 'J', 'O', 'U', 'R', 'N', '1'};
constexpr char kMagicV2[8] = {'S', 'M', 'J', 'O', 'U', 'R', 'N', '2'};
constexpr size_t kMagicBytes = 8;
constexpr uint8_t kMarker[4] = {'S', 'M', 'R', 2};
constexpr size_t kHeaderBytes = 24;   // marker, length, number, body CRC, header CRC
constexpr size_t kV1HeaderBytes = 8;  // length, CRC
constexpr uint32_t kMaxRecordBytes = 64u << 20;
// Types 1-4 were written before samples named their stream (and session events their seq):
// read as stream 0. Types 5-8 carry both.
enum RecordType : uint8_t {
  kCloudFrame = 1,
  kPose = 2,
  kSessionEvent = 3,
  kPoseCorrection = 4,
  kFrameAlignment = 5,  // written as 9 only (the server's record has a header like streams')
  kStreamed = 4,        // added to a type: the same message with its stream
};

// Little-endian field writer/reader; the reader fails (ok() false) on any overrun.
class Writer {
 public:
  template <typename T>
  void put(const T& value) {
    static_assert(std::is_trivially_copyable_v<T>);
    const auto* p = reinterpret_cast<const uint8_t*>(&value);
    bytes.insert(bytes.end(), p, p + sizeof(T));
  }
  void putString(const std::string& s) {
    put(static_cast<uint32_t>(s.size()));
    bytes.insert(bytes.end(), s.begin(), s.end());
  }
  void putBytes(const std::vector<uint8_t>& b) {
    put(static_cast<uint32_t>(b.size()));
    bytes.insert(bytes.end(), b.begin(), b.end());
  }
  std::vector<uint8_t> bytes;
};

class Reader {
 public:
  Reader(const uint8_t* data, size_t size) : data_(data), size_(size) {}
  template <typename T>
  T get() {
    T value{};
    if (at_ + sizeof(T) > size_) {
      ok_ = false;
      return value;
    }
    std::memcpy(&value, data_ + at_, sizeof(T));
    at_ += sizeof(T);
    return value;
  }
  std::string getString() {
    const auto n = get<uint32_t>();
    if (!ok_ || at_ + n > size_) return ok_ = false, std::string();
    std::string s(reinterpret_cast<const char*>(data_ + at_), n);
    at_ += n;
    return s;
  }
  std::vector<uint8_t> getBytes() {
    const auto n = get<uint32_t>();
    if (!ok_ || at_ + n > size_) return ok_ = false, std::vector<uint8_t>();
    std::vector<uint8_t> b(data_ + at_, data_ + at_ + n);
    at_ += n;
    return b;
  }
  bool ok() const { return ok_ && at_ == size_; }
  bool atEnd() const { return at_ >= size_; }

 private:
  const uint8_t* data_;
  size_t size_, at_ = 0;
  bool ok_ = true;
};

template <size_t N>
void putArray(Writer& w, const std::array<double, N>& a) {
  for (double v : a) w.put(v);
}
template <size_t N>
void getArray(Reader& r, std::array<double, N>& a) {
  for (double& v : a) v = r.get<double>();
}

// The fields every message starts with: ids, stream, seq, unacked_from, stamp.
template <typename Message>
void putHeader(Writer& w, const Message& m) {
  w.putString(m.vehicle_id);
  w.putString(m.session_id);
  w.put(m.stream);
  w.put(m.seq);
  w.put(m.unacked_from);
  w.put(m.stamp_ns);
}
// `streamed` false: a record of types 1-4 (no stream; session events without a seq).
template <typename Message>
void getHeader(Reader& r, Message& m, bool streamed) {
  m.vehicle_id = r.getString();
  m.session_id = r.getString();
  if (streamed) m.stream = r.get<uint64_t>();
  if (streamed || !std::is_same_v<Message, proto::SessionEventMsg>) m.seq = r.get<uint64_t>();
  if (streamed) m.unacked_from = r.get<uint64_t>();
  m.stamp_ns = r.get<int64_t>();
}

std::vector<uint8_t> encode(const JournalRecord& record, uint8_t& type) {
  Writer w;
  if (const auto* f = std::get_if<proto::CloudFrameMsg>(&record)) {
    type = kCloudFrame + kStreamed;
    putHeader(w, *f);
    putArray(w, f->sensor_position);
    putArray(w, f->sensor_orientation);
    w.put(f->max_range);
    w.put(f->point_count);
    w.put(static_cast<uint8_t>(f->encoding));
    w.put(f->quantization_bits);
    w.put(static_cast<uint8_t>(f->has_intensity));
    w.putBytes(f->payload);
  } else if (const auto* e = std::get_if<proto::SessionEventMsg>(&record)) {
    type = kSessionEvent + kStreamed;
    putHeader(w, *e);
    w.put(static_cast<uint8_t>(e->kind));
    w.put(e->width);
    w.put(e->height);
    for (double v : {e->fx, e->fy, e->cx, e->cy, e->baseline, e->resolution_hint}) w.put(v);
    // Only when it is not the session's: records of vehicles in the session's frame stay
    // byte for byte what earlier versions wrote (and read).
    if (e->frame != proto::VehicleFrame::kSession) w.put(static_cast<uint8_t>(e->frame));
  } else if (const auto* a = std::get_if<proto::FrameAlignmentMsg>(&record)) {
    type = kFrameAlignment + kStreamed;
    putHeader(w, *a);
    putArray(w, a->position);
    putArray(w, a->orientation);
    w.put(a->overlap);
    w.put(a->rmse_m);
  } else if (const auto* c = std::get_if<proto::PoseCorrectionMsg>(&record)) {
    type = kPoseCorrection + kStreamed;
    putHeader(w, *c);
    w.put(static_cast<uint32_t>(c->keyframes.size()));
    for (const auto& k : c->keyframes) {
      w.put(k.stamp_ns);
      putArray(w, k.position);
      putArray(w, k.orientation);
    }
  } else {
    const auto& p = std::get<proto::PoseMsg>(record);
    type = kPose + kStreamed;
    putHeader(w, p);
    putArray(w, p.position);
    putArray(w, p.orientation);
    putArray(w, p.velocity);
    putArray(w, p.covariance);
    w.put(static_cast<uint8_t>(p.tracking_state));
    w.put(static_cast<uint8_t>(p.source));
  }
  return std::move(w.bytes);
}

bool decode(uint8_t type, const uint8_t* data, size_t size, JournalRecord& out) {
  Reader r(data, size);
  const bool streamed = type > kStreamed;
  if (streamed) type -= kStreamed;
  if (type == kCloudFrame) {
    proto::CloudFrameMsg f;
    getHeader(r, f, streamed);
    getArray(r, f.sensor_position);
    getArray(r, f.sensor_orientation);
    f.max_range = r.get<float>();
    f.point_count = r.get<uint32_t>();
    const uint8_t encoding = r.get<uint8_t>();
    if (encoding > static_cast<uint8_t>(proto::CloudEncoding::kQuantZstd)) return false;
    f.encoding = static_cast<proto::CloudEncoding>(encoding);
    f.quantization_bits = r.get<uint8_t>();
    f.has_intensity = r.get<uint8_t>() != 0;
    f.payload = r.getBytes();
    out = std::move(f);
  } else if (type == kPose) {
    proto::PoseMsg p;
    getHeader(r, p, streamed);
    getArray(r, p.position);
    getArray(r, p.orientation);
    getArray(r, p.velocity);
    getArray(r, p.covariance);
    p.tracking_state = static_cast<proto::TrackingState>(std::min<uint8_t>(r.get<uint8_t>(), 3));
    p.source = static_cast<proto::PoseSource>(std::min<uint8_t>(r.get<uint8_t>(), 2));
    out = std::move(p);
  } else if (type == kSessionEvent) {
    proto::SessionEventMsg e;
    getHeader(r, e, streamed);
    e.kind = static_cast<proto::SessionEventKind>(r.get<uint8_t>() & 1);
    e.width = r.get<uint32_t>();
    e.height = r.get<uint32_t>();
    for (double* v : {&e.fx, &e.fy, &e.cx, &e.cy, &e.baseline, &e.resolution_hint}) {
      *v = r.get<double>();
    }
    if (!r.atEnd()) {
      const uint8_t frame = r.get<uint8_t>();
      if (frame > static_cast<uint8_t>(proto::VehicleFrame::kOwn)) return false;
      e.frame = static_cast<proto::VehicleFrame>(frame);
    }
    out = std::move(e);
  } else if (type == kFrameAlignment && streamed) {
    proto::FrameAlignmentMsg a;
    getHeader(r, a, streamed);
    getArray(r, a.position);
    getArray(r, a.orientation);
    a.overlap = r.get<double>();
    a.rmse_m = r.get<double>();
    out = std::move(a);
  } else if (type == kPoseCorrection) {
    proto::PoseCorrectionMsg c;
    getHeader(r, c, streamed);
    const uint32_t count = r.get<uint32_t>();
    // Bounded before anything is allocated: a damaged count must not ask for gigabytes.
    if (count > proto::kMaxCorrectedKeyframes || count > size / 64) return false;
    c.keyframes.resize(count);
    for (auto& k : c.keyframes) {
      k.stamp_ns = r.get<int64_t>();
      getArray(r, k.position);
      getArray(r, k.orientation);
    }
    out = std::move(c);
  } else {
    return false;
  }
  return r.ok();
}

// Type byte + body, as the record's checksummed payload.
std::vector<uint8_t> payloadOf(const JournalRecord& record) {
  uint8_t type = 0;
  std::vector<uint8_t> body = encode(record, type);
  body.insert(body.begin(), type);
  return body;
}

void putU32(uint8_t* at, uint32_t value) { std::memcpy(at, &value, 4); }
void putU64(uint8_t* at, uint64_t value) { std::memcpy(at, &value, 8); }
uint32_t getU32(const uint8_t* at) {
  uint32_t value;
  std::memcpy(&value, at, 4);
  return value;
}
uint64_t getU64(const uint8_t* at) {
  uint64_t value;
  std::memcpy(&value, at, 8);
  return value;
}

// One format 2 record: header + payload.
std::vector<uint8_t> framed(const std::vector<uint8_t>& payload, uint64_t number) {
  std::vector<uint8_t> bytes(kHeaderBytes + payload.size());
  std::memcpy(bytes.data(), kMarker, 4);
  putU32(&bytes[4], static_cast<uint32_t>(payload.size()));
  putU64(&bytes[8], number);
  putU32(&bytes[16], crc32(payload.data(), payload.size()));
  putU32(&bytes[20], crc32(bytes.data(), 20));
  std::memcpy(&bytes[kHeaderBytes], payload.data(), payload.size());
  return bytes;
}

struct Header {
  uint32_t length = 0;
  uint64_t number = 0;
  uint32_t body_crc = 0;
};

// The format 2 header at `at`, if one is there and its own checksum holds.
std::optional<Header> headerAt(const std::vector<uint8_t>& bytes, size_t at) {
  if (bytes.size() - at < kHeaderBytes || std::memcmp(&bytes[at], kMarker, 4) != 0) return {};
  if (crc32(&bytes[at], 20) != getU32(&bytes[at + 20])) return {};
  Header header{getU32(&bytes[at + 4]), getU64(&bytes[at + 8]), getU32(&bytes[at + 16])};
  if (header.length == 0 || header.length > kMaxRecordBytes || header.number == 0) return {};
  return header;
}

// The next offset at or after `from` where a valid format 2 header starts, or npos.
size_t nextHeader(const std::vector<uint8_t>& bytes, size_t from) {
  const auto begin = bytes.begin() + static_cast<long>(std::min(from, bytes.size()));
  for (auto it = begin; (it = std::search(it, bytes.end(), kMarker, kMarker + 4)) != bytes.end();
       ++it) {
    const size_t at = static_cast<size_t>(it - bytes.begin());
    if (headerAt(bytes, at)) return at;
  }
  return std::string::npos;
}

// Format 2: records with markers and numbers; damage is skipped up to the next valid header.
void readV2(const std::vector<uint8_t>& bytes, size_t start, JournalReplay& replay,
            const JournalVisitor& visit, uint64_t min_number) {
  size_t at = start;
  replay.good_bytes = at;
  while (at < bytes.size()) {
    const auto header = headerAt(bytes, at);
    if (!header) {
      const size_t next = nextHeader(bytes, at + 1);
      if (next == std::string::npos) {
        // Less than a header: a write cut short, never acknowledged. A whole header's worth
        // of bytes that do not read is damage (a flipped byte in the last record): it may be
        // an acknowledged record, so it is set aside, never silently cut.
        if (bytes.size() - at >= kHeaderBytes) {
          replay.damage.push_back({at, bytes.size(), replay.last_number + 1, replay.last_number + 1,
                                   "unreadable bytes at the end"});
          replay.damaged_tail = true;
        }
        break;
      }
      const uint64_t number = getU64(&bytes[next + 8]);
      JournalDamage damage{at, next, replay.last_number + 1, number - 1, "unreadable bytes"};
      if (damage.last_lost < damage.first_lost) damage.first_lost = damage.last_lost = 0;
      replay.damage.push_back(std::move(damage));
      at = next;
      continue;
    }
    const size_t end = at + kHeaderBytes + header->length;
    if (end > bytes.size()) break;  // the record was being written: a torn tail
    const uint8_t* payload = &bytes[at + kHeaderBytes];
    JournalRecord decoded;
    const bool whole = crc32(payload, header->length) == header->body_crc;
    if (whole && header->number < min_number) {
      ++replay.kept;  // checked, not wanted: not decoded
    } else if (whole && decode(payload[0], payload + 1, header->length - 1, decoded)) {
      ++replay.kept;
      visit(std::move(decoded), header->number);
    } else {
      replay.damage.push_back({at, end, header->number, header->number,
                               whole ? "undecodable record" : "checksum mismatch"});
    }
    replay.last_number = std::max(replay.last_number, header->number);
    at = end;
    replay.good_bytes = at;
  }
}

// A whole, checksummed format 1 record at `at`: its length, or 0.
size_t v1RecordAt(const std::vector<uint8_t>& bytes, size_t at, JournalRecord* decoded) {
  if (bytes.size() - at < kV1HeaderBytes + 1) return 0;
  const uint32_t length = getU32(&bytes[at]);
  if (length == 0 || length > kMaxRecordBytes || bytes.size() - at - kV1HeaderBytes < length) {
    return 0;
  }
  const uint8_t* payload = &bytes[at + kV1HeaderBytes];
  // Cheap tests first: the scan below tries every offset.
  if (payload[0] < kCloudFrame || payload[0] > kPoseCorrection + kStreamed) return 0;
  if (crc32(payload, length) != getU32(&bytes[at + 4])) return 0;
  JournalRecord scratch;
  if (!decode(payload[0], payload + 1, length - 1, decoded ? *decoded : scratch)) return 0;
  return kV1HeaderBytes + length;
}

// Format 1: no markers, so after damage every later offset is tried for a whole record.
void readV1(const std::vector<uint8_t>& bytes, size_t start, JournalReplay& replay,
            const JournalVisitor& visit, uint64_t min_number) {
  size_t at = start;
  replay.good_bytes = at;
  uint64_t count = 0;
  while (at < bytes.size()) {
    JournalRecord decoded;
    if (const size_t length = v1RecordAt(bytes, at, &decoded)) {
      ++replay.kept;
      if (++count >= min_number) visit(std::move(decoded), count);
      at += length;
      replay.good_bytes = at;
      continue;
    }
    size_t next = at + 1;
    while (next < bytes.size() && v1RecordAt(bytes, next, nullptr) == 0) ++next;
    if (next >= bytes.size()) break;
    replay.damage.push_back({at, next, 0, 0, "unreadable bytes (format 1: records not numbered)"});
    at = next;
  }
  replay.last_number = count;
}

std::string summary(const JournalReplay& replay) {
  std::string text;
  auto add = [&](const std::string& part) { text += (text.empty() ? "" : "; ") + part; };
  if (replay.header_damaged) add("file header damaged");
  for (const auto& damage : replay.damage) add(damage.describe());
  if (replay.good_bytes < replay.file_bytes && !replay.damaged_tail) {
    add("torn tail at byte " + std::to_string(replay.good_bytes) + " (" +
        std::to_string(replay.file_bytes - replay.good_bytes) + " bytes cut)");
  }
  if (!text.empty()) {
    text += "; kept " + std::to_string(replay.kept) + " records";
    if (const uint64_t lost = replay.lostRecords()) text += ", lost " + std::to_string(lost);
  }
  return text;
}

}  // namespace

std::string JournalDamage::describe() const {
  std::string who;
  if (first_lost == 0) {
    who = "no numbered record lost";
  } else if (first_lost == last_lost) {
    who = "record " + std::to_string(first_lost) + " lost";
  } else {
    who = "records " + std::to_string(first_lost) + "-" + std::to_string(last_lost) + " lost";
  }
  return reason + " at bytes " + std::to_string(begin) + "-" + std::to_string(end) + " (" + who +
         ")";
}

uint64_t JournalReplay::lostRecords() const {
  uint64_t lost = 0;
  for (const auto& d : damage) lost += d.first_lost == 0 ? 0 : d.last_lost - d.first_lost + 1;
  return lost;
}

std::vector<uint8_t> encodeRecord(const JournalRecord& record) { return payloadOf(record); }

std::optional<JournalRecord> decodeRecord(const uint8_t* data, size_t size) {
  JournalRecord record;
  if (size == 0 || !decode(data[0], data + 1, size - 1, record)) return std::nullopt;
  return record;
}

uint32_t crc32(const uint8_t* data, size_t size) {
  static const std::array<uint32_t, 256> table = [] {
    std::array<uint32_t, 256> t{};
    for (uint32_t i = 0; i < 256; ++i) {
      uint32_t c = i;
      for (int k = 0; k < 8; ++k) c = (c & 1) ? 0xEDB88320u ^ (c >> 1) : c >> 1;
      t[i] = c;
    }
    return t;
  }();
  uint32_t c = 0xFFFFFFFFu;
  for (size_t i = 0; i < size; ++i) c = table[(c ^ data[i]) & 0xFF] ^ (c >> 8);
  return c ^ 0xFFFFFFFFu;
}

common::Result<JournalReplay> readJournal(const fs::path& path) {
  JournalReplay replay;
  auto read = visitJournal(path, 0, [&](JournalRecord&& record, uint64_t number) {
    replay.records.push_back(std::move(record));
    replay.numbers.push_back(number);
  });
  if (!read) return read.error();
  read->records = std::move(replay.records);
  read->numbers = std::move(replay.numbers);
  return read;
}

common::Result<JournalReplay> visitJournal(const fs::path& path, uint64_t min_number,
                                           const JournalVisitor& visit, uint64_t from_offset) {
  if (from_offset > kMagicBytes) {
    auto tail = common::readFileFrom(path, from_offset);
    if (!tail) return tail.error();
    JournalReplay replay;
    readV2(*tail, 0, replay, visit, min_number);
    replay.file_bytes = from_offset + tail->size();
    replay.good_bytes += from_offset;
    for (auto& damage : replay.damage) {
      damage.begin += from_offset;
      damage.end += from_offset;
    }
    replay.problem = summary(replay);
    return replay;
  }
  auto read = common::readWholeFile(path);
  if (!read) return read.error();
  const std::vector<uint8_t>& bytes = *read;
  JournalReplay replay;
  replay.file_bytes = bytes.size();
  // A header cut short by a failed first write (a prefix of either magic) is an empty journal.
  if (bytes.size() < kMagicBytes &&
      (bytes.empty() || std::memcmp(bytes.data(), kMagicV1, bytes.size()) == 0 ||
       std::memcmp(bytes.data(), kMagicV2, bytes.size()) == 0)) {
    if (!bytes.empty()) replay.problem = summary(replay);
    return replay;
  }
  const bool v1 =
      bytes.size() >= kMagicBytes && std::memcmp(bytes.data(), kMagicV1, kMagicBytes) == 0;
  const bool v2 =
      bytes.size() >= kMagicBytes && std::memcmp(bytes.data(), kMagicV2, kMagicBytes) == 0;
  if (v1) {
    replay.version = 1;
    readV1(bytes, kMagicBytes, replay, visit, min_number);
  } else {
    // A damaged file header costs nothing when records follow it.
    readV2(bytes, kMagicBytes, replay, visit, min_number);
    replay.header_damaged = !v2;
    if (!v2 && replay.kept == 0) {
      JournalReplay not_ours;
      not_ours.file_bytes = bytes.size();
      not_ours.problem = "not a stereomap journal (bad header); nothing kept";
      return not_ours;
    }
  }
  replay.problem = summary(replay);
  return replay;
}

namespace {

// What Journal::open keeps of a reading: everything but the records, which it never needs.
JournalReplay withoutRecords(const JournalReplay& read) {
  JournalReplay kept;
  kept.version = read.version;
  kept.kept = read.kept;
  kept.damage = read.damage;
  kept.good_bytes = read.good_bytes;
  kept.file_bytes = read.file_bytes;
  kept.last_number = read.last_number;
  kept.header_damaged = read.header_damaged;
  kept.damaged_tail = read.damaged_tail;
  kept.problem = read.problem;
  return kept;
}

}  // namespace

common::Result<std::unique_ptr<Journal>> Journal::open(const fs::path& path, uint64_t first_number,
                                                       const JournalReplay* scanned) {
  auto journal = std::unique_ptr<Journal>(new Journal());
  journal->path_ = path;
  // Every record is checked (a damaged one is found), none is kept: a long journal would
  // otherwise sit in memory whole.
  auto replay = scanned != nullptr ? common::Result<JournalReplay>(withoutRecords(*scanned))
                                   : visitJournal(path, 0, [](JournalRecord&&, uint64_t) {});
  const bool exists = replay || replay.error().code != ErrorCode::kNotFound;
  if (replay) {
    journal->recovered_ = std::move(replay).value();
  } else if (exists) {
    return replay.error();  // unreadable is not missing: never start over on top of it
  }
  auto& recovered = journal->recovered_;
  if (recovered.version == 1 && recovered.good_bytes > 0) {
    return makeError(ErrorCode::kConflict,
                     path.string() + ": a format 1 journal; rewrite it as format 2 first");
  }
  if (recovered.good_bytes == 0 && recovered.file_bytes >= kMagicBytes) {
    // Not ours: refuse rather than overwrite whatever this file is.
    return makeError(ErrorCode::kCorrupt, path.string() + ": " + recovered.problem);
  }
  // O_EXCL: a file that appeared since it was found missing is not overwritten.
  journal->fd_ = ::open(path.c_str(),
                        exists ? O_RDWR | O_CLOEXEC : O_RDWR | O_CREAT | O_EXCL | O_CLOEXEC, 0644);
  if (journal->fd_ < 0) {
    return makeError(ErrorCode::kIo, path.string() + ": cannot open the journal for writing: " +
                                         common::systemError(errno));
  }
  struct stat opened {};
  if (::fstat(journal->fd_, &opened) != 0 ||
      static_cast<uint64_t>(opened.st_size) != recovered.file_bytes) {
    return makeError(ErrorCode::kUnavailable,
                     path.string() + ": the journal changed while it was being opened");
  }
  if (recovered.damaged_tail) {
    if (auto kept = journal->setAsideTail(); !kept) return kept.error();
  }
  const bool fresh = recovered.good_bytes < kMagicBytes;
  journal->bytes_ = fresh ? 0 : recovered.good_bytes;
  journal->needs_cut_ = recovered.file_bytes > journal->bytes_;  // a torn tail or header
  if (journal->needs_cut_ && !journal->cutBack()) {
    return makeError(ErrorCode::kIo,
                     path.string() + ": cannot cut the torn tail: " + common::systemError(errno));
  }
  if (fresh || recovered.header_damaged) {
    const auto* magic = reinterpret_cast<const uint8_t*>(kMagicV2);
    if (!common::writeAllAt(journal->fd_, magic, kMagicBytes, 0) ||
        ::fdatasync(journal->fd_) != 0) {
      const int error = errno;
      if (fresh) journal->cutBack();
      return makeError(ErrorCode::kIo, path.string() + ": cannot write the journal header: " +
                                           common::systemError(error));
    }
    if (fresh) journal->bytes_ = kMagicBytes;
  }
  if (!exists) {  // the new file's name, too, must survive a crash
    const fs::path folder = path.has_parent_path() ? path.parent_path() : fs::path(".");
    if (auto synced = common::syncDirectory(folder); !synced) return synced.error();
  }
  // The damaged tail's record keeps its number: new records never reuse it.
  journal->next_number_ =
      std::max(recovered.last_number + (recovered.damaged_tail ? 2 : 1), first_number);
  return journal;
}

common::Status Journal::setAsideTail() {
  const auto& recovered = recovered_;
  std::string tail(recovered.file_bytes - recovered.good_bytes, '\0');
  size_t done = 0;
  while (done < tail.size()) {
    const ssize_t n = ::pread(fd_, tail.data() + done, tail.size() - done,
                              static_cast<off_t>(recovered.good_bytes + done));
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) {
      return makeError(ErrorCode::kIo, path_.string() + ": cannot read the damaged tail: " +
                                           common::systemError(n == 0 ? EIO : errno));
    }
    done += static_cast<size_t>(n);
  }
  const fs::path tail_path = path_.string() + ".tail-" + std::to_string(recovered.good_bytes);
  if (auto kept = common::writeFileAtomically(tail_path, tail); !kept) {
    return makeError(ErrorCode::kIo, path_.string() +
                                         ": the damaged tail could not be set aside, so it is "
                                         "not cut: " +
                                         kept.error().message);
  }
  recovered_.problem += "; the damaged tail was set aside as " + tail_path.string();
  return common::Ok{};
}

Journal::~Journal() {
  if (fd_ >= 0) ::close(fd_);
}

bool Journal::cutBack() {
  if (::ftruncate(fd_, static_cast<off_t>(bytes_)) != 0 || ::fdatasync(fd_) != 0) return false;
  needs_cut_ = false;
  return true;
}

common::Result<uint64_t> Journal::append(const JournalRecord& record, Durability durability) {
  if (needs_cut_ && !cutBack()) {
    return makeError(ErrorCode::kIo, path_.string() +
                                         ": the journal still ends in a failed write and cannot "
                                         "be cut back: " +
                                         common::systemError(errno));
  }
  const std::vector<uint8_t> bytes = framed(payloadOf(record), next_number_);
  if (!common::writeAllAt(fd_, bytes.data(), bytes.size(), bytes_) ||
      (durability == Durability::kNow && ::fdatasync(fd_) != 0)) {
    const int error = errno;
    needs_cut_ = true;
    cutBack();  // if this fails too, the next append tries again before writing
    return makeError(ErrorCode::kIo,
                     path_.string() + ": journal write failed: " + common::systemError(error));
  }
  bytes_ += bytes.size();
  return next_number_++;
}

common::Status Journal::sync() {
  if (::fdatasync(fd_) != 0) {
    return makeError(ErrorCode::kIo,
                     path_.string() + ": sync failed: " + common::systemError(errno));
  }
  return common::Ok{};
}

common::Status rewriteJournal(const fs::path& path, const std::vector<JournalRecord>& records,
                              const std::vector<uint64_t>& numbers) {
  std::string content(kMagicV2, kMagicBytes);
  for (size_t i = 0; i < records.size(); ++i) {
    const auto bytes = framed(payloadOf(records[i]), numbers[i]);
    content.append(reinterpret_cast<const char*>(bytes.data()), bytes.size());
  }
  return common::writeFileAtomically(path, content);
}

}  // namespace stereomap::proto::journal
