// File-system helpers that report every failure as a value (never throw): atomic whole-file
// writes (temporary file, fsync, rename, fsync of the folder) and directory listings.
#pragma once

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include "common/result.hpp"

namespace stereomap::common {

// Writes `content` to `path` so that a crash or a full disk leaves either the old file or the
// new one, never a mix: written to a temporary file beside it (`path`.tmp-<pid>-<n>, so two
// writers never share one), flushed to disk, renamed over `path`, then the folder flushed. On
// failure the temporary file is removed and the message names the file and the cause
// ("No space left on device").
Status writeFileAtomically(const std::filesystem::path& path, const std::string& content);

// Flushes a folder, making the names created, renamed or removed in it durable.
Status syncDirectory(const std::filesystem::path& dir);

// The whole content of `path`. kNotFound only when the file does not exist (ENOENT); any
// other failure (permissions, EIO while reading) is kIo, so callers never take an unreadable
// file for a missing one.
Result<std::vector<uint8_t>> readWholeFile(const std::filesystem::path& path);
// The same from byte `offset` to the end (empty when the file is shorter).
Result<std::vector<uint8_t>> readFileFrom(const std::filesystem::path& path, uint64_t offset);

// The entries of `dir` (files, folders, links; unsorted). kNotFound or kIo naming the folder.
Result<std::vector<std::filesystem::path>> directoryEntries(const std::filesystem::path& dir);

// Writes all `size` bytes at `offset` of the open file `fd` (pwrite, retried on EINTR and
// short writes); false with errno set when the kernel refuses (ENOSPC, EFBIG, EIO).
bool writeAllAt(int fd, const void* data, size_t size, uint64_t offset);

// errno as text, e.g. "No space left on device".
std::string systemError(int error_number);

}  // namespace stereomap::common
