// OctoMap's complaints reach the server's log (spdlog), line by line, and std::cerr is given
// back afterwards.
#include "server/fusion/octomap_log.hpp"

#include <gtest/gtest.h>
#include <octomap/OcTree.h>
#include <spdlog/sinks/ostream_sink.h>
#include <spdlog/spdlog.h>

#include <sstream>

namespace stereomap::fusion {
namespace {

TEST(OctomapLogRoute, OctomapsWarningsGoToTheLog) {
  std::ostringstream logged;
  const auto previous = spdlog::default_logger();
  spdlog::set_default_logger(std::make_shared<spdlog::logger>(
      "test", std::make_shared<spdlog::sinks::ostream_sink_mt>(logged)));
  std::streambuf* const terminal = std::cerr.rdbuf();
  {
    OctomapLogRoute route;
    octomap::OcTree tree(0.1);
    tree.search(1e6, 0, 0);  // out of the tree's bounds: OctoMap says so on std::cerr
  }
  spdlog::set_default_logger(previous);
  EXPECT_EQ(std::cerr.rdbuf(), terminal);
  EXPECT_NE(logged.str().find("octomap: ERROR: Error in search"), std::string::npos)
      << logged.str();
  EXPECT_NE(logged.str().find("[warning]"), std::string::npos) << logged.str();
}

}  // namespace
}  // namespace stereomap::fusion
