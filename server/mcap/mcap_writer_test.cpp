#include "server/mcap/mcap_writer.hpp"

#include <gtest/gtest.h>
#include <zlib.h>
#include <zstd.h>

#include <cstring>

namespace stereomap::mcap {
namespace {

// A minimal reading of the file along the specification: every record in order, chunks
// decompressed and their CRCs, the data section's and the summary's CRCs checked. (Foxglove's
// own reader reads the exports in tests/interop.)
struct Read {
  std::map<int, int> opcodes;  // top level
  std::map<uint16_t, int> messages;
  std::vector<uint64_t> times;
  bool crcs_ok = true;
  std::string problem;
};

template <typename T>
T get(const std::string& s, size_t at) {
  T value = 0;
  for (size_t i = 0; i < sizeof(T); ++i) {
    value |= static_cast<T>(static_cast<uint8_t>(s[at + i])) << (8 * i);
  }
  return value;
}

uint32_t crc(std::string_view bytes) {
  return static_cast<uint32_t>(::crc32(::crc32(0, nullptr, 0),
                                       reinterpret_cast<const Bytef*>(bytes.data()),
                                       static_cast<uInt>(bytes.size())));
}

void readRecords(const std::string& s, size_t at, size_t end, Read* read, bool top) {
  while (at < end) {
    const int opcode = static_cast<uint8_t>(s[at]);
    const uint64_t length = get<uint64_t>(s, at + 1);
    const size_t content = at + 9;
    if (top) ++read->opcodes[opcode];
    if (opcode == 0x05) {
      ++read->messages[get<uint16_t>(s, content)];
      read->times.push_back(get<uint64_t>(s, content + 6));
    } else if (opcode == 0x06) {
      const uint64_t size = get<uint64_t>(s, content + 16);
      const uint32_t expected = get<uint32_t>(s, content + 24);
      const uint32_t name = get<uint32_t>(s, content + 28);
      const uint64_t compressed = get<uint64_t>(s, content + 32 + name);
      std::string records(size, '\0');
      const size_t got =
          ZSTD_decompress(records.data(), size, s.data() + content + 40 + name, compressed);
      if (ZSTD_isError(got) || got != size || crc(records) != expected) read->crcs_ok = false;
      readRecords(records, 0, records.size(), read, false);
    } else if (opcode == 0x0F) {
      if (get<uint32_t>(s, content) != crc(std::string_view(s).substr(0, at))) {
        read->crcs_ok = false;
      }
    } else if (opcode == 0x02) {
      const uint64_t summary_start = get<uint64_t>(s, content);
      const uint32_t expected = get<uint32_t>(s, content + 16);
      if (crc(std::string_view(s).substr(summary_start, content + 16 - summary_start)) !=
          expected) {
        read->crcs_ok = false;
      }
      return;
    }
    at = content + length;
  }
}

Read readFile(const std::string& file) {
  Read read;
  const std::string magic("\x89MCAP0\r\n", 8);
  if (file.size() < 16 || file.compare(0, 8, magic) != 0 ||
      file.compare(file.size() - 8, 8, magic) != 0) {
    read.problem = "no magic at both ends";
    return read;
  }
  readRecords(file, 8, file.size() - 8, &read, true);
  return read;
}

TEST(McapWriter, ChunksIndexesAndCrcsAlongTheSpecification) {
  std::string file;
  McapWriter mcap(
      [&](std::string_view bytes) {
        file.append(bytes);
        return true;
      },
      {.chunk_bytes = 4096});
  const uint16_t schema = mcap.addSchema("test.Thing", "jsonschema", "{}");
  const uint16_t a = mcap.addChannel(schema, "/a", "json", {{"vehicle", "a"}});
  const uint16_t b = mcap.addChannel(schema, "/b", "json");
  for (uint64_t i = 0; i < 1000; ++i) {
    mcap.write(i % 3 == 0 ? b : a, 1000 + i, "{\"i\":" + std::to_string(i) + "}");
  }
  mcap.attach("map.bt", "application/octet-stream", 1500, std::string(10000, 'x'));
  mcap.metadata("session", {{"id", "s1"}, {"resolution", "0.1"}});
  ASSERT_TRUE(mcap.close());
  EXPECT_EQ(mcap.bytesWritten(), file.size());
  EXPECT_EQ(mcap.messages(), 1000u);

  Read read = readFile(file);
  ASSERT_TRUE(read.problem.empty()) << read.problem;
  EXPECT_TRUE(read.crcs_ok);
  EXPECT_EQ(read.messages.at(a), 666);
  EXPECT_EQ(read.messages.at(b), 334);
  EXPECT_EQ(read.times.front(), 1000u);
  EXPECT_EQ(read.times.back(), 1999u);
  EXPECT_GT(read.opcodes[0x06], 3) << "small chunks: several";
  EXPECT_EQ(read.opcodes[0x06], read.opcodes[0x08]) << "a chunk index per chunk";
  EXPECT_GE(read.opcodes[0x07], read.opcodes[0x06]) << "message indexes after each chunk";
  EXPECT_EQ(read.opcodes[0x09], 1);
  EXPECT_EQ(read.opcodes[0x0A], 1);
  EXPECT_EQ(read.opcodes[0x0C], 1);
  EXPECT_EQ(read.opcodes[0x0B], 1);
  EXPECT_EQ(read.opcodes[0x0F], 1);
  EXPECT_EQ(read.opcodes[0x02], 1);
  EXPECT_EQ(read.opcodes[0x03], 1) << "the schema in the summary";
  EXPECT_EQ(read.opcodes[0x04], 2) << "the channels in the summary";

  // A flipped byte in a chunk is caught by its CRC.
  std::string damaged = file;
  const size_t chunk = damaged.find('\x06', 8 + 9 + 12 + 9);
  ASSERT_NE(chunk, std::string::npos);
  damaged[chunk + 9 + 40 + 4 + 20] ^= 0x01;
  EXPECT_FALSE(readFile(damaged).crcs_ok);
}

TEST(McapWriter, ASinkThatFailsIsAnError) {
  int calls = 0;
  McapWriter mcap([&](std::string_view) { return ++calls < 3; });
  const uint16_t channel = mcap.addChannel(mcap.addSchema("s", "jsonschema", "{}"), "/t", "json");
  for (int i = 0; i < 10; ++i) mcap.write(channel, i, std::string(2u << 20, 'y'));
  const auto closed = mcap.close();
  ASSERT_FALSE(closed);
  EXPECT_EQ(closed.error().code, common::ErrorCode::kIo);
}

}  // namespace
}  // namespace stereomap::mcap
