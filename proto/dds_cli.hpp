// The DDS command-line flags every stereomap binary shares (--dds-config, --domain), for
// app/ folders only (it needs CLI11, which the proto library itself does not link).
#pragma once

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

}  // namespace stereomap::proto
