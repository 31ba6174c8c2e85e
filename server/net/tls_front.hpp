// TLS in front of the HTTP server, in the same process: https and wss on the public address,
// each connection's bytes, once decrypted, relayed to the plain server listening on loopback
// only. One relay serves every protocol the server speaks (REST, the viewer's /ws, Foxglove's
// WebSocket, MCAP downloads streamed from their own threads) without each learning TLS.
// TLS 1.2 and 1.3 only; the certificate file may hold its chain.
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <string>

#include "common/result.hpp"

namespace stereomap::net {

struct TlsFrontOptions {
  std::string address = "127.0.0.1";
  uint16_t port = 8443;       // 0: any free port
  std::string cert_file;      // PEM
  std::string key_file;       // PEM, unencrypted
  uint16_t backend_port = 0;  // the plain server, on 127.0.0.1
  std::chrono::seconds handshake_timeout{10};
  size_t max_connections = 4096;  // beyond: refused at once
};

class TlsFront {
 public:
  // Loads the certificate and key (a clear error naming the file when they do not load or do
  // not match), listens, and serves on a thread of its own.
  static common::Result<std::unique_ptr<TlsFront>> start(const TlsFrontOptions& options);
  ~TlsFront();  // stop()
  TlsFront(const TlsFront&) = delete;
  TlsFront& operator=(const TlsFront&) = delete;
  void stop();
  uint16_t port() const;

 private:
  struct Impl;
  explicit TlsFront(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace stereomap::net
