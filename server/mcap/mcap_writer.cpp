#include "server/mcap/mcap_writer.hpp"

#include <zlib.h>
#include <zstd.h>

namespace stereomap::mcap {

namespace {

constexpr std::string_view kMagic("\x89MCAP0\r\n", 8);

enum Opcode : uint8_t {
  kHeader = 0x01,
  kFooter = 0x02,
  kSchema = 0x03,
  kChannel = 0x04,
  kMessage = 0x05,
  kChunk = 0x06,
  kMessageIndex = 0x07,
  kChunkIndex = 0x08,
  kAttachment = 0x09,
  kAttachmentIndex = 0x0A,
  kStatistics = 0x0B,
  kMetadata = 0x0C,
  kMetadataIndex = 0x0D,
  kSummaryOffset = 0x0E,
  kDataEnd = 0x0F,
};

// Little-endian fields, as the specification's "Serialization" section lays them out.
template <typename T>
void putInt(std::string* out, T value) {
  for (size_t i = 0; i < sizeof(T); ++i)
    out->push_back(static_cast<char>((value >> (8 * i)) & 0xff));
}
void putString(std::string* out, std::string_view s) {
  putInt<uint32_t>(out, static_cast<uint32_t>(s.size()));
  out->append(s);
}
void putStringMap(std::string* out, const std::map<std::string, std::string>& map) {
  std::string entries;
  for (const auto& [key, value] : map) {
    putString(&entries, key);
    putString(&entries, value);
  }
  putString(out, entries);  // a map is prefixed by its byte length, as a string is
}

uint32_t crc32Of(uint32_t crc, std::string_view bytes) {
  // zlib's crc32 takes at most 4 GiB a call.
  while (!bytes.empty()) {
    const size_t n = std::min<size_t>(bytes.size(), 1u << 30);
    crc = static_cast<uint32_t>(
        ::crc32(crc, reinterpret_cast<const Bytef*>(bytes.data()), static_cast<uInt>(n)));
    bytes.remove_prefix(n);
  }
  return crc;
}

}  // namespace

struct McapWriter::Channel {
  uint16_t id;
  std::string record;
  uint32_t sequence = 0;
};

struct McapWriter::ChunkIndex {
  std::string record;
};

McapWriter::McapWriter(Sink sink, McapOptions options)
    : sink_(std::move(sink)), options_(std::move(options)) {
  data_crc_ = crc32Of(0, {});
  put(kMagic);
  std::string header;
  putString(&header, options_.profile);
  putString(&header, options_.library);
  writeRecord(kHeader, header, nullptr);
}

McapWriter::~McapWriter() = default;

void McapWriter::put(std::string_view bytes) {
  if (failed_ || bytes.empty()) return;
  if (!sink_(bytes)) {
    failed_ = true;
    error_ = "the MCAP file could not be written";
    return;
  }
  data_crc_ = crc32Of(data_crc_, bytes);
  offset_ += bytes.size();
}

void McapWriter::writeRecord(uint8_t opcode, std::string_view content, std::string* to) {
  std::string record;
  record.reserve(9 + content.size());
  record.push_back(static_cast<char>(opcode));
  putInt<uint64_t>(&record, content.size());
  record.append(content);
  if (to) {
    to->append(record);
  } else {
    put(record);
  }
}

uint16_t McapWriter::addSchema(const std::string& name, const std::string& encoding,
                               std::string_view data) {
  const auto id = static_cast<uint16_t>(schemas_.size() + 1);
  std::string content;
  putInt<uint16_t>(&content, id);
  putString(&content, name);
  putString(&content, encoding);
  putString(&content, data);
  std::string record;
  writeRecord(kSchema, content, &record);
  chunk_.append(record);  // before the messages that use it, in the chunk they open
  schemas_.push_back({id, std::move(record)});
  return id;
}

uint16_t McapWriter::addChannel(uint16_t schema, const std::string& topic,
                                const std::string& message_encoding,
                                const std::map<std::string, std::string>& metadata) {
  const auto id = static_cast<uint16_t>(channels_.size() + 1);
  std::string content;
  putInt<uint16_t>(&content, id);
  putInt<uint16_t>(&content, schema);
  putString(&content, topic);
  putString(&content, message_encoding);
  putStringMap(&content, metadata);
  std::string record;
  writeRecord(kChannel, content, &record);
  chunk_.append(record);
  channels_.push_back({id, std::move(record)});
  return id;
}

void McapWriter::write(uint16_t channel, uint64_t log_time_ns, std::string_view data,
                       uint64_t publish_time_ns) {
  if (closed_ || channel == 0 || channel > channels_.size()) return;
  Channel& c = channels_[channel - 1];
  if (!chunk_.empty() && chunk_.size() + data.size() > options_.chunk_bytes &&
      chunk_has_messages_) {
    flushChunk();
  }
  std::string content;
  content.reserve(22 + data.size());
  putInt<uint16_t>(&content, channel);
  putInt<uint32_t>(&content, c.sequence++);
  putInt<uint64_t>(&content, log_time_ns);
  putInt<uint64_t>(&content, publish_time_ns ? publish_time_ns : log_time_ns);
  content.append(data);
  chunk_index_[channel].emplace_back(log_time_ns, chunk_.size());
  writeRecord(kMessage, content, &chunk_);
  if (!chunk_has_messages_) {
    chunk_start_ns_ = chunk_end_ns_ = log_time_ns;
  } else {
    chunk_start_ns_ = std::min(chunk_start_ns_, log_time_ns);
    chunk_end_ns_ = std::max(chunk_end_ns_, log_time_ns);
  }
  chunk_has_messages_ = true;
  message_start_ns_ = message_count_ == 0 ? log_time_ns : std::min(message_start_ns_, log_time_ns);
  message_end_ns_ = std::max(message_end_ns_, log_time_ns);
  ++message_count_;
  ++channel_message_counts_[channel];
  if (chunk_.size() >= options_.chunk_bytes) flushChunk();
}

void McapWriter::flushChunk() {
  if (chunk_.empty()) return;
  std::string compressed(ZSTD_compressBound(chunk_.size()), '\0');
  const size_t size = ZSTD_compress(compressed.data(), compressed.size(), chunk_.data(),
                                    chunk_.size(), options_.zstd_level);
  if (ZSTD_isError(size)) {
    failed_ = true;
    error_ = std::string("zstd: ") + ZSTD_getErrorName(size);
    return;
  }
  compressed.resize(size);
  std::string content;
  putInt<uint64_t>(&content, chunk_start_ns_);
  putInt<uint64_t>(&content, chunk_end_ns_);
  putInt<uint64_t>(&content, chunk_.size());
  putInt<uint32_t>(&content, crc32Of(crc32Of(0, {}), chunk_));
  putString(&content, "zstd");
  putInt<uint64_t>(&content, compressed.size());
  content.append(compressed);
  const uint64_t chunk_start = offset_;
  writeRecord(kChunk, content, nullptr);
  const uint64_t chunk_length = offset_ - chunk_start;
  // Each channel's message index, after the chunk (ascending channel id: std::map).
  std::map<uint16_t, uint64_t> index_offsets;
  const uint64_t indexes_start = offset_;
  for (const auto& [channel, entries] : chunk_index_) {
    std::string index;
    putInt<uint16_t>(&index, channel);
    putInt<uint32_t>(&index, static_cast<uint32_t>(entries.size() * 16));
    for (const auto& [time, at] : entries) {
      putInt<uint64_t>(&index, time);
      putInt<uint64_t>(&index, at);
    }
    index_offsets[channel] = offset_;
    writeRecord(kMessageIndex, index, nullptr);
  }
  std::string chunk_index;
  putInt<uint64_t>(&chunk_index, chunk_start_ns_);
  putInt<uint64_t>(&chunk_index, chunk_end_ns_);
  putInt<uint64_t>(&chunk_index, chunk_start);
  putInt<uint64_t>(&chunk_index, chunk_length);
  std::string offsets;
  for (const auto& [channel, at] : index_offsets) {
    putInt<uint16_t>(&offsets, channel);
    putInt<uint64_t>(&offsets, at);
  }
  putString(&chunk_index, offsets);
  putInt<uint64_t>(&chunk_index, offset_ - indexes_start);
  putString(&chunk_index, "zstd");
  putInt<uint64_t>(&chunk_index, compressed.size());
  putInt<uint64_t>(&chunk_index, chunk_.size());
  ChunkIndex entry;
  writeRecord(kChunkIndex, chunk_index, &entry.record);
  chunk_indexes_.push_back(std::move(entry));
  chunk_.clear();
  chunk_index_.clear();
  chunk_has_messages_ = false;
}

void McapWriter::attach(const std::string& name, const std::string& media_type,
                        uint64_t log_time_ns, std::string_view data) {
  if (closed_) return;
  flushChunk();  // attachments live between chunks
  std::string content;
  putInt<uint64_t>(&content, log_time_ns);
  putInt<uint64_t>(&content, log_time_ns);  // create time
  putString(&content, name);
  putString(&content, media_type);
  putInt<uint64_t>(&content, data.size());
  content.append(data);
  putInt<uint32_t>(&content, crc32Of(crc32Of(0, {}), content));
  const uint64_t start = offset_;
  writeRecord(kAttachment, content, nullptr);
  std::string index;
  putInt<uint64_t>(&index, start);
  putInt<uint64_t>(&index, offset_ - start);
  putInt<uint64_t>(&index, log_time_ns);
  putInt<uint64_t>(&index, log_time_ns);
  putInt<uint64_t>(&index, data.size());
  putString(&index, name);
  putString(&index, media_type);
  std::string record;
  writeRecord(kAttachmentIndex, index, &record);
  attachment_indexes_.push_back(std::move(record));
  ++attachment_count_;
}

void McapWriter::metadata(const std::string& name,
                          const std::map<std::string, std::string>& values) {
  if (closed_) return;
  flushChunk();
  std::string content;
  putString(&content, name);
  putStringMap(&content, values);
  const uint64_t start = offset_;
  writeRecord(kMetadata, content, nullptr);
  std::string index;
  putInt<uint64_t>(&index, start);
  putInt<uint64_t>(&index, offset_ - start);
  putString(&index, name);
  std::string record;
  writeRecord(kMetadataIndex, index, &record);
  metadata_indexes_.push_back(std::move(record));
  ++metadata_count_;
}

common::Status McapWriter::close() {
  if (!closed_) {
    closed_ = true;
    flushChunk();
    std::string data_end;
    putInt<uint32_t>(&data_end, data_crc_);
    writeRecord(kDataEnd, data_end, nullptr);

    // The summary: each group of records, and where each group starts.
    const uint64_t summary_start = offset_;
    uint32_t summary_crc = crc32Of(0, {});
    std::string summary_offsets;
    auto group = [&](uint8_t opcode, const auto& records, auto record_of) {
      if (records.empty()) return;
      const uint64_t start = offset_;
      for (const auto& r : records) {
        const std::string& bytes = record_of(r);
        summary_crc = crc32Of(summary_crc, bytes);
        put(bytes);
      }
      std::string entry;
      putInt<uint8_t>(&entry, opcode);
      putInt<uint64_t>(&entry, start);
      putInt<uint64_t>(&entry, offset_ - start);
      writeRecord(kSummaryOffset, entry, &summary_offsets);
    };
    group(kSchema, schemas_, [](const Schema& s) -> const std::string& { return s.record; });
    group(kChannel, channels_, [](const Channel& c) -> const std::string& { return c.record; });
    std::string statistics;
    putInt<uint64_t>(&statistics, message_count_);
    putInt<uint16_t>(&statistics, static_cast<uint16_t>(schemas_.size()));
    putInt<uint32_t>(&statistics, static_cast<uint32_t>(channels_.size()));
    putInt<uint32_t>(&statistics, attachment_count_);
    putInt<uint32_t>(&statistics, metadata_count_);
    putInt<uint32_t>(&statistics, static_cast<uint32_t>(chunk_indexes_.size()));
    putInt<uint64_t>(&statistics, message_start_ns_);
    putInt<uint64_t>(&statistics, message_end_ns_);
    std::string counts;
    for (const auto& [channel, count] : channel_message_counts_) {
      putInt<uint16_t>(&counts, channel);
      putInt<uint64_t>(&counts, count);
    }
    putString(&statistics, counts);
    std::string statistics_record;
    writeRecord(kStatistics, statistics, &statistics_record);
    group(kStatistics, std::vector<std::string>{statistics_record},
          [](const std::string& r) -> const std::string& { return r; });
    group(kChunkIndex, chunk_indexes_,
          [](const ChunkIndex& c) -> const std::string& { return c.record; });
    group(kAttachmentIndex, attachment_indexes_,
          [](const std::string& r) -> const std::string& { return r; });
    group(kMetadataIndex, metadata_indexes_,
          [](const std::string& r) -> const std::string& { return r; });
    const uint64_t summary_offset_start = offset_;
    summary_crc = crc32Of(summary_crc, summary_offsets);
    put(summary_offsets);

    // The footer's CRC covers the summary through the footer's own summary_offset_start.
    std::string footer;
    footer.push_back(static_cast<char>(kFooter));
    putInt<uint64_t>(&footer, 20);
    putInt<uint64_t>(&footer, summary_start);
    putInt<uint64_t>(&footer, summary_offset_start);
    summary_crc = crc32Of(summary_crc, footer);
    putInt<uint32_t>(&footer, summary_crc);
    put(footer);
    put(kMagic);
  }
  if (failed_) return common::makeError(common::ErrorCode::kIo, error_);
  return common::Ok{};
}

}  // namespace stereomap::mcap
