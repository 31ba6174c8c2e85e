#include "common/png.hpp"

#include <zlib.h>

#include <array>

namespace stereomap::common {
namespace {

void putBigEndian32(std::string& out, uint32_t value) {
  for (int shift = 24; shift >= 0; shift -= 8) out.push_back(static_cast<char>(value >> shift));
}

// A chunk: length, type, data, and the CRC of type and data (PNG specification, 5.3).
void putChunk(std::string& out, const char (&type)[5], const std::string& data) {
  putBigEndian32(out, static_cast<uint32_t>(data.size()));
  const size_t type_at = out.size();
  out.append(type, 4);
  out += data;
  const auto* crc_bytes = reinterpret_cast<const Bytef*>(out.data() + type_at);
  putBigEndian32(out,
                 static_cast<uint32_t>(crc32(0, crc_bytes, static_cast<uInt>(4 + data.size()))));
}

}  // namespace

std::string encodeGreyPng(const std::vector<uint8_t>& pixels, uint32_t width, uint32_t height) {
  if (width == 0 || height == 0 || pixels.size() != static_cast<size_t>(width) * height) return {};
  // Every row starts with its filter type; 0 (none) keeps the writer simple, and the rows of
  // a top view are long runs that zlib compresses well without filtering.
  std::string raw;
  raw.reserve(static_cast<size_t>(width + 1) * height);
  for (uint32_t row = 0; row < height; ++row) {
    raw.push_back('\0');
    raw.append(reinterpret_cast<const char*>(pixels.data()) + static_cast<size_t>(row) * width,
               width);
  }
  uLongf packed_size = compressBound(static_cast<uLong>(raw.size()));
  std::string packed(packed_size, '\0');
  if (compress2(reinterpret_cast<Bytef*>(packed.data()), &packed_size,
                reinterpret_cast<const Bytef*>(raw.data()), static_cast<uLong>(raw.size()),
                Z_BEST_SPEED) != Z_OK) {
    return {};
  }
  packed.resize(packed_size);

  std::string header;
  putBigEndian32(header, width);
  putBigEndian32(header, height);
  header +=
      std::string{'\x08', '\x00', '\x00', '\x00', '\x00'};  // 8 bits, grey, deflate, no interlace

  std::string png("\x89PNG\r\n\x1a\n", 8);
  putChunk(png, "IHDR", header);
  putChunk(png, "IDAT", packed);
  putChunk(png, "IEND", {});
  return png;
}

}  // namespace stereomap::common
