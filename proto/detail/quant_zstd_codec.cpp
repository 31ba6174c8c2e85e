// Quantised + delta + zstd: Draco's quantisation grid (the bounding cube split into 2^bits - 1
// steps), the points in the order given, each coordinate as the zigzagged difference from the
// previous point's, split into byte planes (a plane of low bytes, then one of high bytes), then
// one zstd frame. Thinned clouds come in image order, so consecutive points are neighbours and
// the high planes are nearly constant.
//
// Layout, little-endian: u8 version (1), u8 bits, u8 flags (bit 0: intensity), u8 0,
// u32 point count, f32 origin[3], f64 step, then the zstd frame of x planes, y planes,
// z planes and the intensity differences (mod 256).
#include <zstd.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <memory>
#include <string>

#include "proto/detail/codecs.hpp"

namespace stereomap::proto::detail {

using common::ErrorCode;
using common::makeError;
using common::PointCloud;
using common::Result;

namespace {

constexpr uint8_t kVersion = 1;
constexpr size_t kHeaderBytes = 28;
constexpr uint8_t kIntensityFlag = 1;

struct Header {
  uint8_t bits = 0;
  bool intensity = false;
  uint32_t count = 0;
  float origin[3] = {0, 0, 0};
  double step = 1.0;
};

// Bytes each zigzagged difference needs: differences span +-(2^bits - 1).
size_t planesFor(int bits) { return static_cast<size_t>(bits + 1 + 7) / 8; }

uint32_t zigzag(int64_t v) { return static_cast<uint32_t>(v < 0 ? -2 * v - 1 : 2 * v); }
int64_t unzigzag(uint32_t v) { return (v & 1) ? -static_cast<int64_t>(v >> 1) - 1 : v >> 1; }

void putHeader(const Header& h, uint8_t* out) {
  out[0] = kVersion;
  out[1] = h.bits;
  out[2] = h.intensity ? kIntensityFlag : 0;
  out[3] = 0;
  std::memcpy(out + 4, &h.count, 4);
  std::memcpy(out + 8, h.origin, 12);
  std::memcpy(out + 20, &h.step, 8);
}

struct ZstdContexts {
  std::unique_ptr<ZSTD_CCtx, decltype(&ZSTD_freeCCtx)> compress{ZSTD_createCCtx(), &ZSTD_freeCCtx};
  std::unique_ptr<ZSTD_DCtx, decltype(&ZSTD_freeDCtx)> decompress{ZSTD_createDCtx(),
                                                                  &ZSTD_freeDCtx};
};
// One pair per thread: a context holds ~1 MiB of tables, too much to make per cloud.
ZstdContexts& contexts() {
  thread_local ZstdContexts instance;
  return instance;
}

}  // namespace

Result<std::vector<uint8_t>> encodeQuantZstd(const PointCloud& cloud,
                                             const CloudCodecOptions& options) {
  const size_t n = cloud.size();
  const int bits = options.quantization_bits;
  Header header;
  header.bits = static_cast<uint8_t>(bits);
  header.intensity = cloud.hasIntensity();
  header.count = static_cast<uint32_t>(n);
  const uint32_t max_q = (uint32_t{1} << bits) - 1;
  if (n > 0) {
    common::Vec3f lo = cloud.points.front(), hi = lo;
    for (const auto& p : cloud.points) {
      lo = lo.cwiseMin(p);
      hi = hi.cwiseMax(p);
    }
    const double range = (hi.cast<double>() - lo.cast<double>()).maxCoeff();
    for (int c = 0; c < 3; ++c) header.origin[c] = lo[c];
    if (range > 0) header.step = range / max_q;
  }

  const size_t planes = planesFor(bits);
  std::vector<uint8_t> raw(n * (3 * planes + (header.intensity ? 1 : 0)));
  for (int c = 0; c < 3; ++c) {
    uint8_t* out = raw.data() + c * planes * n;
    int64_t previous = 0;
    for (size_t i = 0; i < n; ++i) {
      const double offset =
          (static_cast<double>(cloud.points[i][c]) - header.origin[c]) / header.step;
      const auto q = std::clamp<int64_t>(std::llround(offset), 0, max_q);
      const uint32_t z = zigzag(q - previous);
      previous = q;
      for (size_t b = 0; b < planes; ++b) out[b * n + i] = static_cast<uint8_t>(z >> (8 * b));
    }
  }
  if (header.intensity) {
    uint8_t* out = raw.data() + 3 * planes * n;
    uint8_t previous = 0;
    for (size_t i = 0; i < n; ++i) {
      out[i] = static_cast<uint8_t>(cloud.intensity[i] - previous);
      previous = cloud.intensity[i];
    }
  }

  std::vector<uint8_t> payload(kHeaderBytes + ZSTD_compressBound(raw.size()));
  putHeader(header, payload.data());
  const size_t written =
      ZSTD_compressCCtx(contexts().compress.get(), payload.data() + kHeaderBytes,
                        payload.size() - kHeaderBytes, raw.data(), raw.size(), options.zstd_level);
  if (ZSTD_isError(written)) {
    return makeError(ErrorCode::kInvalidArgument,
                     std::string("zstd compression failed: ") + ZSTD_getErrorName(written));
  }
  payload.resize(kHeaderBytes + written);
  return payload;
}

Result<PointCloud> decodeQuantZstd(std::span<const uint8_t> payload, const CloudPayloadInfo& info) {
  auto corrupt = [](const std::string& what) {
    return makeError(ErrorCode::kCorrupt, "zstd cloud payload: " + what);
  };
  if (payload.size() < kHeaderBytes) return corrupt("shorter than its header");
  if (payload[0] != kVersion) return corrupt("unknown version " + std::to_string(payload[0]));
  Header header;
  header.bits = payload[1];
  if (header.bits < 1 || header.bits > 30) return corrupt("bits out of 1..30");
  if ((payload[2] & ~kIntensityFlag) != 0 || payload[3] != 0) return corrupt("unknown flags");
  header.intensity = (payload[2] & kIntensityFlag) != 0;
  std::memcpy(&header.count, payload.data() + 4, 4);
  std::memcpy(header.origin, payload.data() + 8, 12);
  std::memcpy(&header.step, payload.data() + 20, 8);
  if (header.count != info.point_count) {
    return makeError(ErrorCode::kConflict,
                     "zstd cloud payload holds " + std::to_string(header.count) +
                         " points, point_count says " + std::to_string(info.point_count));
  }
  if (header.intensity != info.has_intensity) return corrupt("intensity differs from the message");
  const uint32_t max_q = (uint32_t{1} << header.bits) - 1;
  for (const float o : header.origin) {
    // The grid's far corner must be a finite float too, so every decoded point is.
    if (!std::isfinite(o) || !(std::abs(o + header.step * max_q) <
                               static_cast<double>(std::numeric_limits<float>::max()))) {
      return corrupt("grid out of range");
    }
  }
  if (!std::isfinite(header.step) || header.step <= 0) return corrupt("step is not positive");

  const size_t n = header.count;
  const size_t planes = planesFor(header.bits);
  const size_t expected = n * (3 * planes + (header.intensity ? 1 : 0));
  const std::span<const uint8_t> frame = payload.subspan(kHeaderBytes);
  if (ZSTD_findFrameCompressedSize(frame.data(), frame.size()) != frame.size()) {
    return corrupt("not exactly one zstd frame");
  }
  // The frame states its size, which must be exactly what the points need: checked before
  // anything is allocated. What the points need is bounded by the caller's bound on
  // point_count (the server's IngestLimits: 13 MB at most).
  if (ZSTD_getFrameContentSize(frame.data(), frame.size()) != expected) {
    return corrupt("frame size differs from the point count's");
  }
  std::vector<uint8_t> raw(expected);
  const size_t got = ZSTD_decompressDCtx(contexts().decompress.get(), raw.data(), raw.size(),
                                         frame.data(), frame.size());
  if (ZSTD_isError(got) || got != expected) return corrupt("zstd frame does not decode");

  PointCloud cloud;
  cloud.points.resize(n);
  for (int c = 0; c < 3; ++c) {
    const uint8_t* in = raw.data() + c * planes * n;
    int64_t q = 0;
    for (size_t i = 0; i < n; ++i) {
      uint32_t z = 0;
      for (size_t b = 0; b < planes; ++b) z |= static_cast<uint32_t>(in[b * n + i]) << (8 * b);
      q += unzigzag(z);
      if (q < 0 || q > max_q) return corrupt("a point leaves the grid");
      cloud.points[i][c] = static_cast<float>(header.origin[c] + header.step * q);
    }
  }
  if (header.intensity) {
    const uint8_t* in = raw.data() + 3 * planes * n;
    cloud.intensity.resize(n);
    uint8_t previous = 0;
    for (size_t i = 0; i < n; ++i) previous = cloud.intensity[i] = previous + in[i];
  }
  return cloud;
}

}  // namespace stereomap::proto::detail
