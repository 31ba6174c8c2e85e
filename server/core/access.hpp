// Who may do what over HTTP and the WebSockets: tokens with a role and a name, kept as SHA-256
// hashes (a stolen list gives no token), checked in time that does not depend on which entry or
// how much of it matched. Two roles: a viewer reads (tiles, /ws, Foxglove live, exports); an
// operator also changes (open, close, delete, merge, align, site: every POST and DELETE under
// /api/sessions). Several tokens per role at once, so one can be rotated without a gap.
//
// The list's file, one token per line (# starts a comment; stereomap-certs token makes lines):
//   operator sha256:9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08 alice
//   viewer   sha256:...                                                              wall-screen
#pragma once

#include <array>
#include <string>
#include <string_view>
#include <vector>

#include "common/result.hpp"

namespace stereomap::core {

enum class Role { kNone, kViewer, kOperator };
const char* roleName(Role role);

struct Grant {
  Role role = Role::kNone;
  std::string name;  // the token's name, for logs; empty for kNone
};

class AccessList {
 public:
  // The lines of a token file (`origin` names it in errors): each "ROLE sha256:HEX NAME".
  static common::Result<AccessList> parse(std::string_view text, const std::string& origin);
  static common::Result<AccessList> load(const std::string& path);
  // A token given in clear (--token, STEREOMAP_TOKEN): kept only as its hash.
  void add(Role role, std::string_view token, std::string name);
  // No token at all: the server is open (allowed on loopback only; the app insists).
  bool empty() const { return entries_.empty(); }
  size_t size() const { return entries_.size(); }
  // The grant of a presented token: every entry is compared, each in constant time.
  Grant check(std::string_view presented) const;
  // What an open server (empty()) grants: everything, to anyone.
  static Grant open() { return {Role::kOperator, "anyone (no tokens set)"}; }
  Grant grant(std::string_view presented) const { return empty() ? open() : check(presented); }

 private:
  struct Entry {
    Role role;
    std::array<unsigned char, 32> hash;
    std::string name;
  };
  std::vector<Entry> entries_;
};

// The SHA-256 of `text` as 64 lowercase hex digits.
std::string sha256Hex(std::string_view text);

}  // namespace stereomap::core
