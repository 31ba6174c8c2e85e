// What the network layer (server/net) asks of a WebSocket protocol, so that one transport
// serves both: our viewer's (/ws, ViewerHub) and Foxglove's (FoxgloveHub). The transport only
// moves bytes: it asks next() for a message whenever its connection is idle, reports what it
// wrote and received, and closes a connection when closing() says so. One thread (the network
// thread) calls everything.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <string_view>

namespace stereomap::viewers {

struct Outgoing {
  std::shared_ptr<const std::string> bytes;
  bool binary = false;  // else JSON text
};

// RFC 6455 close codes used, with the reason sent in the close frame.
struct CloseOrder {
  uint16_t code = 1000;
  std::string reason;
};

class Endpoint {
 public:
  using Id = uint64_t;
  virtual ~Endpoint() = default;
  virtual void disconnect(Id id) = 0;
  virtual void receive(Id id, std::string_view text, int64_t now_ns) = 0;  // a text message
  virtual void receiveBinary(Id id, std::string_view bytes) = 0;           // a binary message
  // Pushes what changed since the last poll and closes stuck or silent connections.
  virtual void poll(int64_t now_ns) = 0;
  // The next message for `id` while none is being written (nullopt: nothing to send now).
  virtual std::optional<Outgoing> next(Id id, int64_t now_ns) = 0;
  virtual void written(Id id) = 0;  // the message from next() has been written
  // Set when the connection must be closed; the transport closes it and calls disconnect().
  virtual std::optional<CloseOrder> closing(Id id) const = 0;
};

}  // namespace stereomap::viewers
