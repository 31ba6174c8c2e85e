// Fuzz target: the viewer WebSocket's control messages (protocol 2, server/viewers'
// ViewerHub) over a real fused session. The input is a conversation: messages separated by
// newlines, sent in turn by one viewer (the first byte says whether its upgrade carried the
// token). After each, everything the hub has queued is drained: each text must be valid JSON
// and each binary message a tile that decodes, and a viewer told to close must stay closed.
#include <nlohmann/json.hpp>

#include "proto/tiles/tile_codec.hpp"
#include "server/viewers/viewer_hub.hpp"
#include "tests/fuzz/fuzz_input.hpp"
#include "tests/fuzz/fuzz_server.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace stereomap;
  static fuzz::IdCheckingAdmin admin;
  viewers::HubOptions options;
  options.access.add(core::Role::kViewer, "secret", "fuzz");
  viewers::ViewerHub hub(fuzz::fusedServer(), &admin, options);
  fuzz::FuzzInput in(data, size);
  const auto id = hub.connect(/*authorised=*/in.byte() & 1, /*now_ns=*/1'000'000'000);
  int64_t now = 1'000'000'000;
  while (in.remaining() > 0 && !hub.closing(id)) {
    hub.receive(id, in.until('\n'), now);
    hub.poll(now);
    while (auto message = hub.next(id, now)) {
      if (message->binary) {
        if (!proto::tiles::decodeTile(*message->bytes)) __builtin_trap();
      } else if (!nlohmann::json::accept(*message->bytes)) {
        __builtin_trap();
      }
      hub.written(id);
    }
    now += 30'000'000;
  }
  hub.disconnect(id);
  return 0;
}
