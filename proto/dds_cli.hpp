// The DDS command-line flags every stereomap binary shares (--dds-config, --domain), for
// app/ folders only (it needs CLI11, which the proto library itself does not link).
#pragma once

#include <spdlog/spdlog.h>
#include <CLI/CLI.hpp>

#include <filesystem>

#include "proto/dds.hpp"

namespace stereomap::proto {

inline void addDdsFlags(CLI::App& app, DdsOptions& options) {
  app.add_option("--dds-config", options.config_file,
                 "Cyclone DDS XML configuration (default: $CYCLONEDDS_URI, else loopback only)")
      ->check(CLI::ExistingFile)
      ->each([&options](const std::string& path) {
        options.config_file = std::filesystem::absolute(path).string();  // Cyclone wants a URI
      });
  app.add_option("--security", options.security_dir,
                 "DDS Security: this participant's folder from stereomap-certs (authenticated, "
                 "encrypted, partitions by signed permissions). Default: none, for loopback "
                 "tests and demos only")
      ->check(CLI::ExistingDirectory)
      ->each([&options](const std::string& path) {
        options.security_dir = std::filesystem::absolute(path).string();
      });
  app.add_option("--domain", options.domain_id, "DDS domain id")
      ->check(CLI::Range(0, 232))
      ->capture_default_str();
}

// Says at start what in the --security folder runs out within two weeks (a warning) or has run
// out (an error: Cyclone refuses an expired certificate, and past its CRL's next update every
// handshake fails, without saying why).
inline void logSecurityDates(const DdsOptions& options) {
  if (options.security_dir.empty()) return;
  constexpr std::chrono::hours kAhead{14 * 24};
  for (const auto& line : securityDatesDue(options.security_dir, kAhead)) {
    if (line.find("ran out") != std::string::npos) {
      spdlog::error("{}", line);
    } else {
      spdlog::warn("{}", line);
    }
  }
}

}  // namespace stereomap::proto
