#include "common/files.hpp"

#include <fcntl.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstring>

namespace stereomap::common {

namespace fs = std::filesystem;

std::string systemError(int error_number) { return std::strerror(error_number); }

bool writeAllAt(int fd, const void* data, size_t size, uint64_t offset) {
  const auto* bytes = static_cast<const char*>(data);
  while (size > 0) {
    const ssize_t n = ::pwrite(fd, bytes, size, static_cast<off_t>(offset));
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) {
      if (n == 0) errno = EIO;
      return false;
    }
    bytes += n;
    size -= static_cast<size_t>(n);
    offset += static_cast<uint64_t>(n);
  }
  return true;
}

Status syncDirectory(const fs::path& dir) {
  const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (fd < 0)
    return makeError(ErrorCode::kIo, "cannot open " + dir.string() + ": " + systemError(errno));
  const bool synced = ::fsync(fd) == 0;
  const int error = errno;
  ::close(fd);
  if (!synced)
    return makeError(ErrorCode::kIo, "cannot flush " + dir.string() + ": " + systemError(error));
  return Ok{};
}

Result<std::vector<uint8_t>> readWholeFile(const fs::path& path) { return readFileFrom(path, 0); }

Result<std::vector<uint8_t>> readFileFrom(const fs::path& path, uint64_t offset) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    const int error = errno;
    return makeError(error == ENOENT ? ErrorCode::kNotFound : ErrorCode::kIo,
                     "cannot open " + path.string() + ": " + systemError(error));
  }
  std::vector<uint8_t> bytes;
  uint8_t buffer[1 << 16];
  if (offset > 0 && ::lseek(fd, static_cast<off_t>(offset), SEEK_SET) < 0) {
    const int error = errno;
    ::close(fd);
    return makeError(ErrorCode::kIo, "cannot read " + path.string() + ": " + systemError(error));
  }
  for (;;) {
    const ssize_t n = ::read(fd, buffer, sizeof(buffer));
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) {
      const int error = errno;
      ::close(fd);
      return makeError(ErrorCode::kIo, "cannot read " + path.string() + ": " + systemError(error));
    }
    if (n == 0) break;
    bytes.insert(bytes.end(), buffer, buffer + n);
  }
  ::close(fd);
  return bytes;
}

Status writeFileAtomically(const fs::path& path, const std::string& content) {
  static std::atomic<uint64_t> counter{0};
  const fs::path temporary = path.string() + ".tmp-" + std::to_string(::getpid()) + "-" +
                             std::to_string(counter.fetch_add(1));
  const int fd = ::open(temporary.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) {
    return makeError(ErrorCode::kIo,
                     "cannot create " + temporary.string() + ": " + systemError(errno));
  }
  const bool written = writeAllAt(fd, content.data(), content.size(), 0) && ::fsync(fd) == 0;
  int error = errno;
  const bool closed = ::close(fd) == 0;
  if (written && !closed) error = errno;
  if (!written || !closed) {
    ::unlink(temporary.c_str());
    return makeError(ErrorCode::kIo, "cannot write " + path.string() + ": " + systemError(error));
  }
  if (::rename(temporary.c_str(), path.c_str()) != 0) {
    const int rename_error = errno;
    ::unlink(temporary.c_str());
    return makeError(ErrorCode::kIo, "cannot rename " + temporary.string() + " to " +
                                         path.string() + ": " + systemError(rename_error));
  }
  // The rename itself is durable only once the folder is.
  return syncDirectory(path.has_parent_path() ? path.parent_path() : fs::path("."));
}

Result<std::vector<fs::path>> directoryEntries(const fs::path& dir) {
  std::error_code ec;
  std::vector<fs::path> entries;
  fs::directory_iterator it(dir, ec);
  for (; !ec && it != fs::directory_iterator(); it.increment(ec)) entries.push_back(it->path());
  if (ec) {
    return makeError(
        ec == std::errc::no_such_file_or_directory ? ErrorCode::kNotFound : ErrorCode::kIo,
        "cannot list " + dir.string() + ": " + ec.message());
  }
  return entries;
}

}  // namespace stereomap::common
