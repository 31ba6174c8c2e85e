// The parts of an HTTP request the server reads itself: percent escapes, query parameters and
// header lists. Both refuse what they cannot read rather than guess.
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

// Whether a header's comma-separated list ("foxglove.sdk.v1, foxglove.websocket.v1") holds
// `token` as one of its items (spaces and tabs around items ignored; case matters).
bool listsToken(std::string_view list, std::string_view token);

// Compares in time that depends only on the lengths, so that a secret (a token) cannot be
// guessed byte by byte from response times.
bool sameSecret(std::string_view given, std::string_view expected);

// A text from the network as it may go into a log: printable ASCII, anything else '?'.
std::string printable(std::string_view text);

}  // namespace stereomap::common
