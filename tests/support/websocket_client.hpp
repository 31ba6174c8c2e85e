// A minimal WebSocket client (RFC 6455) over a blocking loopback socket, for cross-process
// tests that need full control of what is sent, including frames a browser never would
// (oversized, unmasked, binary). Not for production use.
#pragma once

#include <chrono>
#include <cstdint>
#include <optional>
#include <string>

namespace stereomap::testing {

struct WsMessage {
  enum class Kind { kText, kBinary, kClose, kNone } kind = Kind::kNone;  // kNone: timed out or lost
  std::string payload;                                                   // kClose: the reason
  uint16_t close_code = 0;
};

class WebSocketClient {
 public:
  // Connects and upgrades at `path` (e.g. "/ws"); `headers` are extra request lines ending in
  // \r\n. status() is the HTTP status of the upgrade (101 when it worked).
  WebSocketClient(int port, const std::string& path = "/ws", const std::string& headers = "");
  ~WebSocketClient();
  WebSocketClient(const WebSocketClient&) = delete;
  WebSocketClient& operator=(const WebSocketClient&) = delete;

  int status() const { return status_; }
  bool sendText(const std::string& text) { return sendFrame(0x1, text); }
  bool sendBinary(const std::string& bytes) { return sendFrame(0x2, bytes); }
  // One frame with this opcode, masked as clients must (unless `masked` is false).
  bool sendFrame(uint8_t opcode, const std::string& payload, bool masked = true);
  // The next message (pings are answered, fragments joined); kNone after `timeout`.
  WsMessage read(std::chrono::milliseconds timeout = std::chrono::milliseconds(5000));
  // Reads until a text message containing `needle` (or a close, or the timeout).
  WsMessage readUntil(const std::string& needle,
                      std::chrono::milliseconds timeout = std::chrono::milliseconds(5000));

 private:
  bool readExactly(void* data, size_t size, std::chrono::steady_clock::time_point deadline);
  int fd_ = -1;
  int status_ = 0;
  std::string pending_;  // bytes read past the upgrade response
};

}  // namespace stereomap::testing
