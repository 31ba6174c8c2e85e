#include "server/core/access.hpp"

#include <openssl/crypto.h>
#include <openssl/evp.h>

#include <cctype>
#include <fstream>
#include <sstream>

namespace stereomap::core {

namespace {

std::array<unsigned char, 32> sha256(std::string_view text) {
  std::array<unsigned char, 32> digest{};
  unsigned int length = 0;
  EVP_Digest(text.data(), text.size(), digest.data(), &length, EVP_sha256(), nullptr);
  return digest;
}

bool parseHex(std::string_view hex, std::array<unsigned char, 32>& out) {
  if (hex.size() != 64) return false;
  for (size_t i = 0; i < 32; ++i) {
    unsigned value = 0;
    for (char c : hex.substr(2 * i, 2)) {
      value <<= 4;
      if (c >= '0' && c <= '9') {
        value |= static_cast<unsigned>(c - '0');
      } else if (c >= 'a' && c <= 'f') {
        value |= static_cast<unsigned>(c - 'a' + 10);
      } else {
        return false;
      }
    }
    out[i] = static_cast<unsigned char>(value);
  }
  return true;
}

bool validName(const std::string& name) {
  if (name.empty() || name.size() > 64) return false;
  for (char c : name) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '.' && c != '_' && c != '-' &&
        c != '@') {
      return false;
    }
  }
  return true;
}

}  // namespace

const char* roleName(Role role) {
  switch (role) {
    case Role::kViewer:
      return "viewer";
    case Role::kOperator:
      return "operator";
    case Role::kNone:
      break;
  }
  return "none";
}

std::string sha256Hex(std::string_view text) {
  static constexpr char kDigits[] = "0123456789abcdef";
  std::string hex;
  for (unsigned char byte : sha256(text)) {
    hex += kDigits[byte >> 4];
    hex += kDigits[byte & 15];
  }
  return hex;
}

common::Result<AccessList> AccessList::parse(std::string_view text, const std::string& origin) {
  AccessList list;
  std::istringstream lines{std::string(text)};
  std::string line;
  for (int number = 1; std::getline(lines, line); ++number) {
    if (const auto hash = line.find('#'); hash != std::string::npos) line.erase(hash);
    std::istringstream words(line);
    std::string role, digest, name, extra;
    if (!(words >> role)) continue;  // blank or a comment
    const std::string where = origin + ":" + std::to_string(number) + ": ";
    if (!(words >> digest >> name) || (words >> extra)) {
      return common::makeError(common::ErrorCode::kInvalidArgument,
                               where + "want 'ROLE sha256:HEX NAME' (stereomap-certs token)");
    }
    Entry entry;
    if (role == "viewer") {
      entry.role = Role::kViewer;
    } else if (role == "operator") {
      entry.role = Role::kOperator;
    } else {
      return common::makeError(
          common::ErrorCode::kInvalidArgument,
          where + "the role is 'viewer' or 'operator', not '" + role.substr(0, 32) + "'");
    }
    if (!digest.starts_with("sha256:") || !parseHex(digest.substr(7), entry.hash)) {
      return common::makeError(common::ErrorCode::kInvalidArgument,
                               where + "the token's hash is sha256: and 64 lowercase hex digits");
    }
    if (!validName(name)) {
      return common::makeError(common::ErrorCode::kInvalidArgument,
                               where + "a token's name is 1-64 of [A-Za-z0-9._@-]");
    }
    entry.name = name;
    list.entries_.push_back(std::move(entry));
  }
  return list;
}

common::Result<AccessList> AccessList::load(const std::string& path) {
  std::ifstream in(path);
  if (!in) {
    return common::makeError(common::ErrorCode::kNotFound, "cannot read the token file " + path);
  }
  std::ostringstream text;
  text << in.rdbuf();
  return parse(text.str(), path);
}

void AccessList::add(Role role, std::string_view token, std::string name) {
  entries_.push_back({role, sha256(token), std::move(name)});
}

Grant AccessList::check(std::string_view presented) const {
  if (presented.empty()) return {};
  const auto digest = sha256(presented);
  const Entry* match = nullptr;
  for (const auto& entry : entries_) {
    // Every entry compared in full; which one matched changes no timing but this pointer.
    const bool same = CRYPTO_memcmp(entry.hash.data(), digest.data(), digest.size()) == 0;
    match = same ? &entry : match;
  }
  if (match == nullptr) return {};
  return {match->role, match->name};
}

}  // namespace stereomap::core
