// The command-line parse every stereomap binary does the same way, with CLI11: --help prints
// and exits 0, bad usage prints CLI11's message and exits 2 (STYLE.md: 2 for bad usage).
//
//   if (auto exit_code = common::parseCommandLine(app, argc, argv)) return *exit_code;
#pragma once

#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <optional>
#include <sstream>
#include <string>

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

// An option that is "auto" (the program works it out) or a number: the number, or nullopt for
// "auto" and for text that is no finite number whole (never throws: "nan", "1e400", "12x",
// "99999999999" for an int are refused by autoOr() before anything converts them).
inline std::optional<double> autoOrNumber(const std::string& text) {
  if (text.empty() || text == "auto") return std::nullopt;
  char* end = nullptr;
  errno = 0;
  const double value = std::strtod(text.c_str(), &end);
  if (errno != 0 || end != text.c_str() + text.size() || !std::isfinite(value)) {
    return std::nullopt;
  }
  return value;
}

// The check for such an option: "auto", or a finite number in [min, max], a whole multiple of
// `multiple` when it is > 0.
inline CLI::Validator autoOr(double min, double max, double multiple = 0) {
  const auto shown = [](double v) {
    std::ostringstream out;
    out << v;
    return out.str();
  };
  return CLI::Validator(
      [=](std::string& text) -> std::string {
        if (text == "auto") return {};
        const auto value = autoOrNumber(text);
        if (!value || *value < min || *value > max) {
          return "'" + text.substr(0, 40) + "' is neither auto nor a number from " + shown(min) +
                 " to " + shown(max);
        }
        if (multiple > 0 && std::fmod(*value, multiple) != 0) {
          return "'" + text.substr(0, 40) + "' is not a multiple of " + shown(multiple);
        }
        return {};
      },
      multiple > 0 ? "auto or a multiple of " + shown(multiple) + " in [" + shown(min) + ", " +
                         shown(max) + "]"
                   : "auto or a number in [" + shown(min) + ", " + shown(max) + "]");
}

}  // namespace stereomap::common
