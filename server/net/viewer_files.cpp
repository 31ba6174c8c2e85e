#include "server/net/viewer_files.hpp"

#include <algorithm>
#include <fstream>
#include <iterator>
#include <optional>

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

int hexValue(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  return -1;
}

// "%41" -> "A"; nullopt for a broken escape or an encoded NUL.
std::optional<std::string> percentDecoded(std::string_view text) {
  std::string out;
  out.reserve(text.size());
  for (size_t i = 0; i < text.size(); ++i) {
    if (text[i] != '%') {
      out += text[i];
      continue;
    }
    if (i + 2 >= text.size()) return std::nullopt;
    const int high = hexValue(text[i + 1]), low = hexValue(text[i + 2]);
    if (high < 0 || low < 0 || (high == 0 && low == 0)) return std::nullopt;
    out += static_cast<char>(high * 16 + low);
    i += 2;
  }
  return out;
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
      continue;
    }
    if (!it->is_regular_file(ec)) continue;  // follows a link to see what it names
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
  auto path = percentDecoded(target.substr(0, target.find_first_of("?#")));
  if (!path || path->empty() || path->front() != '/') return nullptr;
  if (path->back() == '/') *path += "index.html";
  const auto found = files_.find(*path);
  return found == files_.end() ? nullptr : &found->second;
}

}  // namespace stereomap::net
