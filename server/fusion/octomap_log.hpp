// OctoMap reports warnings and errors on std::cerr (OCTOMAP_WARNING_STR, OCTOMAP_ERROR_STR).
// The server's log is spdlog's: this sends each such line there, as a warning prefixed
// "octomap: ", so that operators see it with the rest, timestamped, in one stream.
//
//   fusion::OctomapLogRoute route;  // in main(): std::cerr goes to the log until it ends
#pragma once

#include <iostream>
#include <memory>

namespace stereomap::fusion {

class OctomapLogRoute {
 public:
  OctomapLogRoute();
  ~OctomapLogRoute();  // std::cerr writes to the terminal again
  OctomapLogRoute(const OctomapLogRoute&) = delete;
  OctomapLogRoute& operator=(const OctomapLogRoute&) = delete;

 private:
  std::unique_ptr<std::streambuf> to_log_;
  std::streambuf* previous_ = nullptr;
};

}  // namespace stereomap::fusion
