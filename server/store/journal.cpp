#include "server/store/journal.hpp"

#include <unistd.h>

#include <array>
#include <cstring>
#include <fstream>

namespace stereomap::store {

namespace fs = std::filesystem;
using common::ErrorCode;
using common::makeError;

namespace {

constexpr char kMagic[8] = {'S', 'M', 'J', 'O', 'U', 'R', 'N', '1'};
constexpr uint32_t kMaxRecordBytes = 64u << 20;
enum RecordType : uint8_t { kCloudFrame = 1, kPose = 2, kSessionEvent = 3 };

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

// The fields every message starts with: ids, seq (where the message has one), stamp.
template <typename Message>
void putHeader(Writer& w, const Message& m) {
  w.putString(m.vehicle_id);
  w.putString(m.session_id);
  if constexpr (requires { m.seq; }) w.put(m.seq);
  w.put(m.stamp_ns);
}
template <typename Message>
void getHeader(Reader& r, Message& m) {
  m.vehicle_id = r.getString();
  m.session_id = r.getString();
  if constexpr (requires { m.seq; }) m.seq = r.get<uint64_t>();
  m.stamp_ns = r.get<int64_t>();
}

std::vector<uint8_t> encode(const JournalRecord& record, uint8_t& type) {
  Writer w;
  if (const auto* f = std::get_if<proto::CloudFrameMsg>(&record)) {
    type = kCloudFrame;
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
    type = kSessionEvent;
    putHeader(w, *e);
    w.put(static_cast<uint8_t>(e->kind));
    w.put(e->width);
    w.put(e->height);
    for (double v : {e->fx, e->fy, e->cx, e->cy, e->baseline, e->resolution_hint}) w.put(v);
  } else {
    const auto& p = std::get<proto::PoseMsg>(record);
    type = kPose;
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
  if (type == kCloudFrame) {
    proto::CloudFrameMsg f;
    getHeader(r, f);
    getArray(r, f.sensor_position);
    getArray(r, f.sensor_orientation);
    f.max_range = r.get<float>();
    f.point_count = r.get<uint32_t>();
    f.encoding = static_cast<proto::CloudEncoding>(r.get<uint8_t>() & 1);
    f.quantization_bits = r.get<uint8_t>();
    f.has_intensity = r.get<uint8_t>() != 0;
    f.payload = r.getBytes();
    out = std::move(f);
  } else if (type == kPose) {
    proto::PoseMsg p;
    getHeader(r, p);
    getArray(r, p.position);
    getArray(r, p.orientation);
    getArray(r, p.velocity);
    getArray(r, p.covariance);
    p.tracking_state = static_cast<proto::TrackingState>(std::min<uint8_t>(r.get<uint8_t>(), 3));
    p.source = static_cast<proto::PoseSource>(std::min<uint8_t>(r.get<uint8_t>(), 2));
    out = std::move(p);
  } else if (type == kSessionEvent) {
    proto::SessionEventMsg e;
    getHeader(r, e);
    e.kind = static_cast<proto::SessionEventKind>(r.get<uint8_t>() & 1);
    e.width = r.get<uint32_t>();
    e.height = r.get<uint32_t>();
    for (double* v : {&e.fx, &e.fy, &e.cx, &e.cy, &e.baseline, &e.resolution_hint}) {
      *v = r.get<double>();
    }
    out = std::move(e);
  } else {
    return false;
  }
  return r.ok();
}

}  // namespace

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
  std::ifstream in(path, std::ios::binary);
  if (!in) return makeError(ErrorCode::kNotFound, path.string() + ": cannot open the journal");
  std::vector<uint8_t> bytes((std::istreambuf_iterator<char>(in)),
                             std::istreambuf_iterator<char>());
  JournalReplay replay;
  replay.file_bytes = bytes.size();
  if (bytes.size() < sizeof(kMagic) || std::memcmp(bytes.data(), kMagic, sizeof(kMagic)) != 0) {
    if (bytes.empty()) return replay;  // created but never written: an empty journal
    replay.problem = "not a stereomap journal (bad header); nothing kept";
    return replay;
  }
  size_t at = sizeof(kMagic);
  replay.good_bytes = at;
  // Record: u32 length, u32 CRC-32 of (type + body), u8 type, body.
  while (at < bytes.size()) {
    const size_t record = at;
    if (bytes.size() - at < 9) {
      replay.problem = "torn record header at byte " + std::to_string(record);
      break;
    }
    uint32_t length, checksum;
    std::memcpy(&length, &bytes[at], 4);
    std::memcpy(&checksum, &bytes[at + 4], 4);
    at += 8;
    if (length == 0 || length > kMaxRecordBytes) {
      replay.problem = "impossible record length " + std::to_string(length) + " at byte " +
                       std::to_string(record);
      break;
    }
    if (bytes.size() - at < length) {
      replay.problem = "torn record at byte " + std::to_string(record) + " (" +
                       std::to_string(bytes.size() - at) + " of " + std::to_string(length) +
                       " bytes)";
      break;
    }
    if (crc32(&bytes[at], length) != checksum) {
      replay.problem = "checksum mismatch in the record at byte " + std::to_string(record);
      break;
    }
    JournalRecord decoded;
    if (!decode(bytes[at], &bytes[at + 1], length - 1, decoded)) {
      replay.problem = "undecodable record at byte " + std::to_string(record);
      break;
    }
    replay.records.push_back(std::move(decoded));
    at += length;
    replay.good_bytes = at;
  }
  if (!replay.problem.empty()) {
    replay.problem += "; cut " + std::to_string(replay.file_bytes - replay.good_bytes) +
                      " bytes, kept " + std::to_string(replay.records.size()) + " records";
  }
  return replay;
}

common::Result<std::unique_ptr<Journal>> Journal::open(const fs::path& path) {
  auto journal = std::unique_ptr<Journal>(new Journal());
  journal->path_ = path;
  std::error_code ec;
  if (fs::exists(path, ec)) {
    auto replay = readJournal(path);
    if (!replay) return replay.error();
    journal->recovered_ = std::move(replay).value();
    if (journal->recovered_.good_bytes == 0 && journal->recovered_.file_bytes > 0) {
      // Not ours: refuse rather than overwrite whatever this file is.
      return makeError(ErrorCode::kCorrupt, path.string() + ": " + journal->recovered_.problem);
    }
    if (journal->recovered_.good_bytes < journal->recovered_.file_bytes) {
      fs::resize_file(path, journal->recovered_.good_bytes, ec);
      if (ec) {
        return makeError(ErrorCode::kIo,
                         path.string() + ": cannot cut the damaged tail: " + ec.message());
      }
    }
  }
  journal->file_ = std::fopen(path.c_str(), "ab");
  if (journal->file_ == nullptr) {
    return makeError(ErrorCode::kIo, path.string() + ": cannot open the journal for writing");
  }
  journal->bytes_ = journal->recovered_.good_bytes;
  if (journal->bytes_ == 0) {
    if (std::fwrite(kMagic, 1, sizeof(kMagic), journal->file_) != sizeof(kMagic) ||
        std::fflush(journal->file_) != 0) {
      return makeError(ErrorCode::kIo, path.string() + ": cannot write the journal header");
    }
    journal->bytes_ = sizeof(kMagic);
  }
  return journal;
}

Journal::~Journal() {
  if (file_ != nullptr) std::fclose(file_);
}

common::Status Journal::append(const JournalRecord& record) {
  uint8_t type = 0;
  std::vector<uint8_t> body = encode(record, type);
  body.insert(body.begin(), type);
  const uint32_t length = static_cast<uint32_t>(body.size());
  const uint32_t checksum = crc32(body.data(), body.size());
  if (std::fwrite(&length, 4, 1, file_) != 1 || std::fwrite(&checksum, 4, 1, file_) != 1 ||
      std::fwrite(body.data(), 1, body.size(), file_) != body.size() || std::fflush(file_) != 0 ||
      ::fdatasync(::fileno(file_)) != 0) {
    return makeError(ErrorCode::kIo, path_.string() + ": journal write failed");
  }
  bytes_ += 8 + body.size();
  return common::Ok{};
}

}  // namespace stereomap::store
