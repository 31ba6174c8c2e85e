// What the fuzz targets share: typed values read off the fuzzer's bytes (FuzzInput, zeros
// once the bytes run out, so every input is a valid sequence of values), and a scratch file
// for parsers that only take a path (one per process, so parallel fuzzing jobs never meet).
#pragma once

#include <unistd.h>

#include <algorithm>
#include <array>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>
#include <string_view>
#include <type_traits>
#include <vector>

namespace stereomap::fuzz {

class FuzzInput {
 public:
  FuzzInput(const uint8_t* data, size_t size) : data_(data), size_(size) {}

  size_t remaining() const { return size_ - at_; }

  template <class T>
  T take() {
    static_assert(std::is_trivially_copyable_v<T>);
    T value{};
    const size_t n = std::min(sizeof(T), remaining());
    std::memcpy(&value, data_ + at_, n);
    at_ += n;
    return value;
  }
  uint8_t byte() { return take<uint8_t>(); }
  template <size_t N>
  void fill(std::array<double, N>& values) {
    for (auto& v : values) v = take<double>();
  }
  // A length byte (at most `max`), then that many bytes.
  std::string string(size_t max = 255) {
    const size_t n = std::min<size_t>({byte(), max, remaining()});
    std::string s(reinterpret_cast<const char*>(data_ + at_), n);
    at_ += n;
    return s;
  }
  // Bytes up to the next `separator` (not included; the separator is consumed) or the end.
  std::string_view until(char separator) {
    const auto* begin = reinterpret_cast<const char*>(data_ + at_);
    const std::string_view rest(begin, remaining());
    const size_t end = std::min(rest.find(separator), rest.size());
    at_ += std::min(end + 1, rest.size());
    return rest.substr(0, end);
  }
  std::vector<uint8_t> rest() {
    std::vector<uint8_t> bytes(data_ + at_, data_ + size_);
    at_ = size_;
    return bytes;
  }
  std::string_view restText() {
    const std::string_view text(reinterpret_cast<const char*>(data_ + at_), remaining());
    at_ = size_;
    return text;
  }

 private:
  const uint8_t* data_;
  size_t size_;
  size_t at_ = 0;
};

// A directory of this process's own under the temporary directory, emptied on first use and
// removed at exit; write() puts bytes in a file there and returns its path.
class ScratchDir {
 public:
  ScratchDir()
      : path_(std::filesystem::temp_directory_path() /
              ("stereomap-fuzz-" + std::to_string(::getpid()))) {
    std::filesystem::remove_all(path_);
    std::filesystem::create_directories(path_);
  }
  ~ScratchDir() {
    std::error_code ignored;
    std::filesystem::remove_all(path_, ignored);
  }
  const std::filesystem::path& path() const { return path_; }
  std::filesystem::path write(const std::string& name, std::string_view bytes) const {
    const auto file = path_ / name;
    std::ofstream(file, std::ios::binary | std::ios::trunc)
        .write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
    return file;
  }

 private:
  std::filesystem::path path_;
};

// One scratch directory per process (a function-local static: made on first use).
inline const ScratchDir& scratch() {
  static const ScratchDir dir;
  return dir;
}

}  // namespace stereomap::fuzz
