#include "server/fusion/octomap_log.hpp"

#include <spdlog/spdlog.h>

#include <string>

namespace stereomap::fusion {

namespace {

// Collects characters per thread (fusion workers write at once) and logs each whole line.
class LineToLog : public std::streambuf {
 protected:
  int_type overflow(int_type c) override {
    thread_local std::string line;
    if (traits_type::eq_int_type(c, traits_type::eof())) return traits_type::not_eof(c);
    const char ch = traits_type::to_char_type(c);
    if (ch == '\n') {
      if (!line.empty()) spdlog::warn("octomap: {}", line);
      line.clear();
    } else if (line.size() < 4096) {
      line.push_back(ch);
    }
    return c;
  }
};

}  // namespace

OctomapLogRoute::OctomapLogRoute()
    : to_log_(std::make_unique<LineToLog>()), previous_(std::cerr.rdbuf(to_log_.get())) {}

OctomapLogRoute::~OctomapLogRoute() { std::cerr.rdbuf(previous_); }

}  // namespace stereomap::fusion
