// The parts of an HTTP request target the server reads itself: percent escapes and query
// parameters. Both refuse what they cannot read rather than guess.
#pragma once

#include <optional>
#include <string>
#include <string_view>

namespace stereomap::common {

// "%41" -> "A"; nullopt for a broken escape or an encoded NUL.
std::optional<std::string> percentDecoded(std::string_view text);

// The decoded value of the query parameter `name` in `target` ("/ws?a=1&token=x%2By" ->
// "x+y"); nullopt when absent or undecodable. Only whole names match ("xtoken" is not
// "token"); the first of repeated names wins.
std::optional<std::string> queryParameter(std::string_view target, std::string_view name);

// Compares in time that depends only on the lengths, so that a secret (a token) cannot be
// guessed byte by byte from response times.
bool sameSecret(std::string_view given, std::string_view expected);

}  // namespace stereomap::common
