// The server's one network port (Boost.Beast): the REST API (server/core/api.hpp), the
// viewer's static files, the viewer WebSocket at /ws (protocol 2, whose logic is
// server/viewers' ViewerHub) and Foxglove's WebSocket protocol at / or /foxglove for clients
// that offer its subprotocol (server/viewers' FoxgloveHub). Runs on its own thread; owns everything
// network-side. See docs/PROTOCOL.md.
//
//   auto http = HttpServer::create({.address = "127.0.0.1", .port = 8080}, map_server);
//   (*http)->start();  ...  (*http)->stop();
#pragma once

#include <chrono>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <string>
#include <string_view>

#include "common/result.hpp"
#include "server/core/access.hpp"
#include "server/core/map_server.hpp"
#include "server/core/session_admin.hpp"

namespace stereomap::net {

struct HttpServerOptions {
  std::string address = "127.0.0.1";
  uint16_t port = 8080;            // 0: any free port (see port())
  std::filesystem::path web_root;  // the built viewer (index.html + assets)
  // https and wss (net::TlsFront) on address:port when both are set: the plain server then
  // listens on 127.0.0.1 only, on a port of its own, behind it.
  std::string tls_cert, tls_key;
  // Who may read and who may change (as "Authorization: Bearer T" or "?token=T"); empty: anyone
  // may do anything (the app allows that on a loopback address only).
  core::AccessList access;
  // How often viewers get what changed (tiles, poses, statuses): the floor of their latency.
  std::chrono::milliseconds push_interval{25};
  // A viewer whose write has not finished this long, or with this much JSON unsent, is
  // closed with the reason (the others never wait for it).
  std::chrono::milliseconds stuck_after{10'000};
  size_t max_queued_bytes = 4u << 20;
  // GET /api/sessions/{id}/session.mcap: writes that session's MCAP through the sink (false:
  // the client is gone), streamed on a thread of its own (streamed_downloads.hpp). Empty: not
  // offered (501).
  std::function<common::Status(const std::string& session,
                               const std::function<bool(std::string_view)>& sink)>
      session_mcap;
};

class HttpServer {
 public:
  // Binds the port (fails with a clear message if it is taken or the address is bad).
  // `admin` (not owned, may be null) serves session management (open, close, delete, merge).
  static common::Result<std::unique_ptr<HttpServer>> create(const HttpServerOptions& options,
                                                            const core::MapServer& server,
                                                            core::SessionAdmin* admin = nullptr);
  ~HttpServer();          // stops
  void start();           // serves on a background thread
  void stop();            // closes the port and every connection; idempotent
  uint16_t port() const;  // the public one (TLS's when set)
  size_t viewers() const;
  // "https" or "http", and "wss" or "ws": how clients reach port().
  const char* scheme() const;
  const char* wsScheme() const;

 private:
  struct Impl;
  explicit HttpServer(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace stereomap::net
