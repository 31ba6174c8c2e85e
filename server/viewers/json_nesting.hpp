// How deeply a JSON text nests arrays and objects (strings skipped), to refuse hostile nesting
// before a parser sees it (both WebSocket protocols: viewer_hub, foxglove_hub).
#pragma once

#include <string_view>

namespace stereomap::viewers {

int jsonNesting(std::string_view text);

}  // namespace stereomap::viewers
