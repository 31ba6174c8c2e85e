#include "tests/support/websocket_client.hpp"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cstring>
#include <random>

namespace stereomap::testing {

using Clock = std::chrono::steady_clock;

WebSocketClient::WebSocketClient(int port, const std::string& path, const std::string& headers) {
  fd_ = ::socket(AF_INET, SOCK_STREAM, 0);
  if (fd_ < 0) return;
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(static_cast<uint16_t>(port));
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (::connect(fd_, reinterpret_cast<sockaddr*>(&address), sizeof(address)) != 0) return;
  const std::string request =
      "GET " + path +
      " HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\n"
      "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
      "Sec-WebSocket-Version: 13\r\n" +
      headers + "\r\n";
  if (::send(fd_, request.data(), request.size(), MSG_NOSIGNAL) !=
      static_cast<ssize_t>(request.size())) {
    return;
  }
  const auto deadline = Clock::now() + std::chrono::seconds(5);
  std::string response;
  while (response.find("\r\n\r\n") == std::string::npos && Clock::now() < deadline) {
    char buffer[4096];
    pollfd p{fd_, POLLIN, 0};
    if (::poll(&p, 1, 100) <= 0) continue;
    const ssize_t n = ::recv(fd_, buffer, sizeof(buffer), 0);
    if (n <= 0) break;
    response.append(buffer, static_cast<size_t>(n));
  }
  const size_t end = response.find("\r\n\r\n");
  if (response.rfind("HTTP/1.1 ", 0) == 0) status_ = std::atoi(response.c_str() + 9);
  if (end != std::string::npos) pending_ = response.substr(end + 4);
}

WebSocketClient::~WebSocketClient() {
  if (fd_ >= 0) ::close(fd_);
}

bool WebSocketClient::sendFrame(uint8_t opcode, const std::string& payload, bool masked) {
  std::string frame;
  frame += static_cast<char>(0x80 | opcode);
  const uint8_t mask_bit = masked ? 0x80 : 0;
  if (payload.size() < 126) {
    frame += static_cast<char>(mask_bit | payload.size());
  } else if (payload.size() < 65536) {
    frame += static_cast<char>(mask_bit | 126);
    frame += static_cast<char>(payload.size() >> 8);
    frame += static_cast<char>(payload.size() & 0xFF);
  } else {
    frame += static_cast<char>(mask_bit | 127);
    for (int shift = 56; shift >= 0; shift -= 8)
      frame += static_cast<char>((payload.size() >> shift) & 0xFF);
  }
  std::string body = payload;
  if (masked) {
    const uint8_t key[4] = {0x12, 0x34, 0x56, 0x78};
    frame.append(reinterpret_cast<const char*>(key), 4);
    for (size_t i = 0; i < body.size(); ++i) body[i] = static_cast<char>(body[i] ^ key[i % 4]);
  }
  frame += body;
  size_t sent = 0;
  while (sent < frame.size()) {
    const ssize_t n = ::send(fd_, frame.data() + sent, frame.size() - sent, MSG_NOSIGNAL);
    if (n <= 0) return false;
    sent += static_cast<size_t>(n);
  }
  return true;
}

bool WebSocketClient::readExactly(void* data, size_t size, Clock::time_point deadline) {
  auto* out = static_cast<char*>(data);
  const size_t from_pending = std::min(size, pending_.size());
  std::memcpy(out, pending_.data(), from_pending);
  pending_.erase(0, from_pending);
  size_t done = from_pending;
  while (done < size) {
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now());
    if (left.count() <= 0) return false;
    pollfd p{fd_, POLLIN, 0};
    const bool ready = ::poll(&p, 1, static_cast<int>(left.count())) > 0;
    const ssize_t n = ready ? ::recv(fd_, out + done, size - done, 0) : 0;
    if (n <= 0) {
      pending_.insert(0, out, done);  // what was read stays for the next read
      return false;
    }
    done += static_cast<size_t>(n);
  }
  return true;
}

WsMessage WebSocketClient::read(std::chrono::milliseconds timeout) {
  const auto deadline = Clock::now() + timeout;
  WsMessage message;
  std::string joined;
  uint8_t first_opcode = 0;
  // The bytes of this message read so far: a timeout in its middle puts them back, so that
  // the next read starts at the message's first byte, not in the middle of a frame (which
  // then read a payload length from tile bytes: found by the soak run).
  std::string consumed;
  auto timedOut = [&] {
    pending_.insert(0, consumed);
    return WsMessage{};
  };
  for (;;) {
    uint8_t head[2];
    if (fd_ < 0 || !readExactly(head, 2, deadline)) return timedOut();
    consumed.append(reinterpret_cast<const char*>(head), 2);
    uint64_t length = head[1] & 0x7F;
    if (length == 126 || length == 127) {
      uint8_t ext[8];
      const size_t n = length == 126 ? 2 : 8;
      if (!readExactly(ext, n, deadline)) return timedOut();
      consumed.append(reinterpret_cast<const char*>(ext), n);
      length = 0;
      for (size_t i = 0; i < n; ++i) length = (length << 8) | ext[i];
    }
    if (length > (1ull << 30)) {  // not a frame this server sends: the stream is lost
      ::close(fd_);
      fd_ = -1;
      return {};
    }
    std::string payload(length, '\0');
    if (length > 0 && !readExactly(payload.data(), length, deadline)) return timedOut();
    consumed += payload;
    const uint8_t opcode = head[0] & 0x0F;
    if (opcode == 0x9) {  // ping: answer, read on
      sendFrame(0xA, payload);
      continue;
    }
    if (opcode == 0xA) continue;
    if (opcode == 0x8) {
      message.kind = WsMessage::Kind::kClose;
      if (payload.size() >= 2) {
        message.close_code = static_cast<uint16_t>((static_cast<uint8_t>(payload[0]) << 8) |
                                                   static_cast<uint8_t>(payload[1]));
        message.payload = payload.substr(2);
      }
      return message;
    }
    if (opcode != 0) first_opcode = opcode;
    joined += payload;
    if (head[0] & 0x80) {
      message.kind = first_opcode == 0x2 ? WsMessage::Kind::kBinary : WsMessage::Kind::kText;
      message.payload = std::move(joined);
      return message;
    }
  }
}

WsMessage WebSocketClient::readUntil(const std::string& needle, std::chrono::milliseconds timeout) {
  const auto deadline = Clock::now() + timeout;
  for (;;) {
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now());
    if (left.count() <= 0) return {};
    auto message = read(left);
    if (message.kind == WsMessage::Kind::kNone || message.kind == WsMessage::Kind::kClose) {
      return message;
    }
    if (message.kind == WsMessage::Kind::kText &&
        message.payload.find(needle) != std::string::npos) {
      return message;
    }
  }
}

}  // namespace stereomap::testing
