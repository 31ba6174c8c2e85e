#include "server/net/viewer_files.hpp"

#include "common/url.hpp"

#include <algorithm>
#include <fstream>
#include <iterator>

namespace stereomap::net {

namespace fs = std::filesystem;

namespace {

std::string_view mimeType(const fs::path& path) {
  const std::string ext = path.extension().string();
  if (ext == ".html") return "text/html; charset=utf-8";
  if (ext == ".js" || ext == ".mjs") return "text/javascript; charset=utf-8";
  if (ext == ".css") return "text/css; charset=utf-8";
  if (ext == ".json" || ext == ".map") return "application/json";
  if (ext == ".svg") return "image/svg+xml";
  if (ext == ".png") return "image/png";
  if (ext == ".ico") return "image/x-icon";
  if (ext == ".wasm") return "application/wasm";
  return "application/octet-stream";
}

bool isInside(const fs::path& path, const fs::path& root) {
  const auto [root_end, _] = std::mismatch(root.begin(), root.end(), path.begin(), path.end());
  return root_end == root.end();
}

}  // namespace

ViewerFiles ViewerFiles::load(const fs::path& root, uint64_t max_file_bytes) {
  ViewerFiles index;
  std::error_code ec;
  index.root_ = fs::canonical(root, ec);
  if (ec || !fs::is_directory(index.root_, ec)) {
    index.root_ = root;
    return index;
  }
  // Directory links are not followed: a link out of the folder must not widen what is served.
  fs::recursive_directory_iterator it(index.root_, fs::directory_options::skip_permission_denied,
                                      ec);
  for (; !ec && it != fs::recursive_directory_iterator(); it.increment(ec)) {
    const fs::path relative = it->path().lexically_relative(index.root_);
    const std::string name = relative.generic_string();
    if (name.empty() || name[0] == '.' || name.find("/.") != std::string::npos) {
      if (it->is_directory(ec)) it.disable_recursion_pending();
      ec.clear();
      continue;
    }
    // Follows a link to see what it names; a dangling one (ENOENT) must not end the scan.
    if (!it->is_regular_file(ec)) {
      ec.clear();
      continue;
    }
    const fs::path target = fs::canonical(it->path(), ec);
    uint64_t size = ec ? 0 : fs::file_size(target, ec);
    if (ec || !isInside(target, index.root_) || size > max_file_bytes) {
      ++index.skipped_;
      ec.clear();
      continue;
    }
    std::ifstream in(target, std::ios::binary);
    File file{std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()),
              std::string(mimeType(target))};
    if (!in.good() && !in.eof()) {
      ++index.skipped_;
      continue;
    }
    size = file.content.size();
    index.bytes_ += size;
    index.files_.emplace("/" + name, std::move(file));
  }
  return index;
}

const ViewerFiles::File* ViewerFiles::find(std::string_view target) const {
  auto path = common::percentDecoded(target.substr(0, target.find_first_of("?#")));
  if (!path || path->empty() || path->front() != '/') return nullptr;
  if (path->back() == '/') *path += "index.html";
  const auto found = files_.find(*path);
  return found == files_.end() ? nullptr : &found->second;
}

}  // namespace stereomap::net
