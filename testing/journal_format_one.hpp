// Tests only: the format 1 journal (before issue 13) holding the records of a format 2 one,
// to check that stores written before format 2 are still read and upgraded right.
#pragma once

#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include "proto/journal/journal.hpp"

namespace stereomap::testing {

// Format 1: each record's payload behind an 8-byte header (length, CRC), no record numbers.
// `starts` (optional) gets the offset of each record in the result.
inline std::string formatOneOf(const std::filesystem::path& format_two,
                               std::vector<size_t>* starts = nullptr) {
  std::ifstream in(format_two, std::ios::binary);
  const std::string v2((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  std::string v1 = "SMJOURN1";
  for (size_t at = 8; at + 24 <= v2.size();) {  // format 2: a 24-byte header per record
    uint32_t length = 0;
    std::memcpy(&length, &v2[at + 4], 4);
    const std::string payload = v2.substr(at + 24, length);
    const uint32_t crc =
        proto::journal::crc32(reinterpret_cast<const uint8_t*>(payload.data()), payload.size());
    if (starts != nullptr) starts->push_back(v1.size());
    v1.append(reinterpret_cast<const char*>(&length), 4);
    v1.append(reinterpret_cast<const char*>(&crc), 4);
    v1 += payload;
    at += 24 + length;
  }
  return v1;
}

}  // namespace stereomap::testing
