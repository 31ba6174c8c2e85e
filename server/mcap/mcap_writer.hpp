// An MCAP file writer (https://mcap.dev/spec, version 0), written from the specification:
// the file Foxglove, Lichtblick and rosbag2 read. Messages go into chunks compressed with
// zstd, each followed by its message indexes; attachments and metadata between chunks; then
// the summary (schemas, channels, statistics, chunk, attachment and metadata indexes, and the
// offsets of each group) and the footer. Every chunk, attachment, the data section and the
// summary carry a CRC-32. Memory is bounded by one chunk and the indexes (a few dozen bytes per
// chunk, attachment and channel): the file is written as it goes.
//
//   McapWriter mcap([&](std::string_view bytes) { return out.write(...).good(); });
//   const uint16_t schema = mcap.addSchema("foxglove.PointCloud", "protobuf", descriptors);
//   const uint16_t channel = mcap.addChannel(schema, "/drone1/cloud", "protobuf");
//   mcap.write(channel, log_time_ns, encoded);
//   mcap.close();
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <string>
#include <string_view>
#include <vector>

#include "common/result.hpp"

namespace stereomap::mcap {

struct McapOptions {
  std::string profile;  // "" (none), "ros2", ...
  std::string library = "stereomap";
  size_t chunk_bytes = 1u << 20;  // uncompressed records per chunk (a message larger goes alone)
  int zstd_level = 3;
};

class McapWriter {
 public:
  // `sink` takes the file's bytes in order; false ends writing with an error (kIo).
  using Sink = std::function<bool(std::string_view bytes)>;
  explicit McapWriter(Sink sink, McapOptions options = {});
  ~McapWriter();
  McapWriter(const McapWriter&) = delete;
  McapWriter& operator=(const McapWriter&) = delete;

  // Ids from 1. A channel's metadata is free-form (key, value) text.
  uint16_t addSchema(const std::string& name, const std::string& encoding, std::string_view data);
  uint16_t addChannel(uint16_t schema, const std::string& topic,
                      const std::string& message_encoding,
                      const std::map<std::string, std::string>& metadata = {});
  // Times in nanoseconds; the sequence counts per channel unless given.
  void write(uint16_t channel, uint64_t log_time_ns, std::string_view data,
             uint64_t publish_time_ns = 0);
  void attach(const std::string& name, const std::string& media_type, uint64_t log_time_ns,
              std::string_view data);
  void metadata(const std::string& name, const std::map<std::string, std::string>& values);

  // Ends the data section and writes the summary and footer. The first failure of the sink or
  // of compression, if any (later calls then do nothing).
  common::Status close();

  uint64_t bytesWritten() const { return offset_; }
  uint64_t messages() const { return message_count_; }

 private:
  struct ChunkIndex;
  struct Channel;
  void put(std::string_view bytes);  // to the sink, counted and in the data section's CRC
  void flushChunk();
  void writeRecord(uint8_t opcode, std::string_view content, std::string* to);

  Sink sink_;
  McapOptions options_;
  bool failed_ = false, closed_ = false;
  std::string error_;
  uint64_t offset_ = 0;
  uint32_t data_crc_ = 0;

  struct Schema {
    uint16_t id;
    std::string record;  // its whole record, for the summary
  };
  std::vector<Schema> schemas_;
  std::vector<Channel> channels_;

  // The open chunk: its records, each channel's (log time, offset) and its time span.
  std::string chunk_;
  std::map<uint16_t, std::vector<std::pair<uint64_t, uint64_t>>> chunk_index_;
  uint64_t chunk_start_ns_ = 0, chunk_end_ns_ = 0;
  bool chunk_has_messages_ = false;

  std::vector<ChunkIndex> chunk_indexes_;
  std::vector<std::string> attachment_indexes_, metadata_indexes_;  // whole records
  uint64_t message_count_ = 0, message_start_ns_ = 0, message_end_ns_ = 0;
  uint32_t attachment_count_ = 0, metadata_count_ = 0;
  std::map<uint16_t, uint64_t> channel_message_counts_;
};

}  // namespace stereomap::mcap
