// The command-line parse every stereomap binary does the same way, with CLI11: --help prints
// and exits 0, bad usage prints CLI11's message and exits 2 (STYLE.md: 2 for bad usage).
//
//   if (auto exit_code = common::parseCommandLine(app, argc, argv)) return *exit_code;
#pragma once

#include <optional>

#include <CLI/CLI.hpp>

namespace stereomap::common {

// nullopt: parsed, go on; otherwise the code to exit with (the message is printed).
inline std::optional<int> parseCommandLine(CLI::App& app, int argc, char** argv) {
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& error) {
    return app.exit(error) == 0 ? 0 : 2;
  }
  return std::nullopt;
}

}  // namespace stereomap::common
