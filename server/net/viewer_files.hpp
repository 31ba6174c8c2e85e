// The built viewer's files, read into memory once at start-up: the only files the server
// ever serves. A request names one by its URL path and is answered from this index, so no
// request path (whatever its encoding, slashes, dots or links) ever reaches the file system.
//
//   auto viewer = ViewerFiles::load("build/web");
//   if (const auto* file = viewer.find("/assets/index.js?v=1")) respond(file->content);
#pragma once

#include <cstdint>
#include <filesystem>
#include <map>
#include <string>
#include <string_view>

namespace stereomap::net {

class ViewerFiles {
 public:
  struct File {
    std::string content;
    std::string content_type;
  };

  // Every regular file under `root`, keyed by its URL path ("/index.html",
  // "/assets/x.js"). A symbolic link is kept only when its target is a regular file inside
  // `root`; dot files, files over `max_file_bytes` and anything unreadable are left out
  // (and counted in skipped()). A missing root gives an empty index.
  static ViewerFiles load(const std::filesystem::path& root, uint64_t max_file_bytes = 64ull << 20);

  // The file for a request target ("/", "/a/", "/x.js?q#f", percent-encoded names), or
  // nullptr when it names no viewer file. A path ending in "/" means its index.html.
  const File* find(std::string_view target) const;

  const std::filesystem::path& root() const { return root_; }
  size_t size() const { return files_.size(); }
  uint64_t bytes() const { return bytes_; }
  size_t skipped() const { return skipped_; }

 private:
  std::filesystem::path root_;
  std::map<std::string, File, std::less<>> files_;
  uint64_t bytes_ = 0;
  size_t skipped_ = 0;
};

}  // namespace stereomap::net
