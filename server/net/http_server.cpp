#include <utility>  // before Boost.Asio: g++ 12 in C++20 needs std::exchange declared first

#include "server/net/http_server.hpp"

#include <spdlog/spdlog.h>
#include <boost/asio.hpp>
#include <boost/beast.hpp>
#include <nlohmann/json.hpp>

#include <atomic>
#include <functional>
#include <mutex>
#include <optional>
#include <set>
#include <thread>

#include "common/time.hpp"
#include "common/url.hpp"
#include "server/core/api.hpp"
#include "server/core/validate.hpp"
#include "server/net/admin_worker.hpp"
#include "server/net/listen.hpp"
#include "server/net/streamed_downloads.hpp"
#include "server/net/tls_front.hpp"
#include "server/net/viewer_files.hpp"
#include "server/viewers/foxglove_hub.hpp"
#include "server/viewers/viewer_hub.hpp"

namespace stereomap::net {

namespace asio = boost::asio;
namespace beast = boost::beast;
namespace http = beast::http;
namespace websocket = beast::websocket;
using tcp = asio::ip::tcp;

namespace {

constexpr size_t kMaxRequestBodyBytes = size_t{64} * 1024;
constexpr auto kIdleTimeout = std::chrono::seconds(60);

std::string tokenFrom(const http::request<http::string_body>& request) {
  const std::string auth(request[http::field::authorization]);
  if (auth.starts_with("Bearer ")) return auth.substr(7);
  const std::string_view target(request.target().data(), request.target().size());
  return common::queryParameter(target, "token").value_or("");
}

using core::errorBody;

}  // namespace

class WebSocketSession;

// Shared by every connection; touched only on the io thread.
struct Hub {
  const core::MapServer& server;
  core::SessionAdmin* admin;  // may be null
  HttpServerOptions options;
  viewers::ViewerHub viewers;
  viewers::FoxgloveHub foxglove;
  ViewerFiles files;
  std::map<const WebSocketSession*, std::shared_ptr<WebSocketSession>> connections;
  std::atomic<size_t> viewer_count{0};
  AdminWorker admin_worker;
  StreamedDownloads downloads;
};

// One WebSocket of either protocol: moves its endpoint's messages (server/viewers: ours, /ws,
// or Foxglove's) to the socket, one write at a time, and the client's messages to the
// endpoint.
class WebSocketSession : public std::enable_shared_from_this<WebSocketSession> {
 public:
  using Connect = std::function<viewers::Endpoint::Id()>;
  // `subprotocol`: the one chosen from the client's offer ("": none).
  WebSocketSession(tcp::socket socket, Hub& hub, viewers::Endpoint& endpoint,
                   std::string subprotocol)
      : ws_(std::move(socket)),
        hub_(hub),
        endpoint_(endpoint),
        subprotocol_(std::move(subprotocol)) {}

  void start(const http::request<http::string_body>& request, Connect connect) {
    ws_.set_option(websocket::stream_base::timeout::suggested(beast::role_type::server));
    if (!subprotocol_.empty()) {
      ws_.set_option(websocket::stream_base::decorator(
          [chosen = subprotocol_](websocket::response_type& response) {
            response.set(http::field::sec_websocket_protocol, chosen);
          }));
    }
    ws_.read_message_max(kMaxRequestBodyBytes);
    ws_.async_accept(
        request, [self = shared_from_this(), connect = std::move(connect)](beast::error_code ec) {
          if (ec) return;
          self->id_ = connect();
          self->hub_.connections[self.get()] = self;
          self->hub_.viewer_count = self->hub_.connections.size();
          self->read();
          self->pump();
        });
  }

  // Writes the hub's next message when none is in flight; closes when the hub says so.
  void pump() {
    if (finished_) return;
    if (auto order = endpoint_.closing(id_)) return closeWith(*order);
    if (writing_) return;
    auto message = endpoint_.next(id_, common::nowNs());
    if (!message) return;
    writing_ = true;
    ws_.binary(message->binary);
    ws_.async_write(
        asio::buffer(*message->bytes),
        [self = shared_from_this(), bytes = message->bytes](beast::error_code ec, size_t) {
          self->writing_ = false;
          if (ec) return self->finish();
          self->endpoint_.written(self->id_);
          self->pump();
        });
  }

  // Drops the connection at once (server shutdown, a failed read or write).
  void finish() {
    if (finished_) return;
    finished_ = true;
    endpoint_.disconnect(id_);
    hub_.connections.erase(this);
    hub_.viewer_count = hub_.connections.size();
    beast::error_code ignored;
    beast::get_lowest_layer(ws_).socket().shutdown(tcp::socket::shutdown_both, ignored);
    beast::get_lowest_layer(ws_).socket().close(ignored);
  }

 private:
  // A close frame with the reason when the line is free; a viewer that does not read gets
  // the socket closed (its close frame could never be written).
  void closeWith(const viewers::CloseOrder& order) {
    if (closing_) return;
    closing_ = true;
    spdlog::warn("{} {}: closing ({})", subprotocol_.empty() ? "viewer" : "foxglove client", id_,
                 order.reason);
    if (writing_) return finish();
    beast::get_lowest_layer(ws_).expires_after(std::chrono::seconds(2));
    ws_.async_close(
        websocket::close_reason(static_cast<websocket::close_code>(order.code), order.reason),
        [self = shared_from_this()](beast::error_code) { self->finish(); });
  }

  void read() {
    ws_.async_read(buffer_, [self = shared_from_this()](beast::error_code ec, size_t) {
      if (ec) {
        // A frame over the limit: say why before the line goes (1009, RFC 6455).
        if (ec == websocket::error::message_too_big) {
          spdlog::warn("viewer {}: message over {} bytes; closing", self->id_,
                       kMaxRequestBodyBytes);
        }
        return self->finish();
      }
      const std::string bytes = beast::buffers_to_string(self->buffer_.data());
      if (self->ws_.got_text()) {
        self->endpoint_.receive(self->id_, bytes, common::nowNs());
      } else {
        self->endpoint_.receiveBinary(self->id_, bytes);
      }
      self->buffer_.consume(self->buffer_.size());
      self->pump();
      if (!self->finished_ && !self->closing_) self->read();
    });
  }

  websocket::stream<beast::tcp_stream> ws_;
  Hub& hub_;
  viewers::Endpoint& endpoint_;
  const std::string subprotocol_;
  viewers::Endpoint::Id id_ = 0;
  beast::flat_buffer buffer_;
  bool writing_ = false, closing_ = false, finished_ = false;
};

class HttpSession : public std::enable_shared_from_this<HttpSession> {
 public:
  HttpSession(tcp::socket socket, Hub& hub) : stream_(std::move(socket)), hub_(hub) {}
  void start() { read(); }

 private:
  void read() {
    parser_.emplace();
    parser_->body_limit(kMaxRequestBodyBytes);
    stream_.expires_after(kIdleTimeout);
    http::async_read(stream_, buffer_, *parser_,
                     [self = shared_from_this()](beast::error_code ec, size_t) {
                       if (ec == http::error::end_of_stream) return self->closeWrite();
                       if (ec) {
                         if (ec != beast::error::timeout && ec != asio::error::operation_aborted) {
                           self->sendError(http::status::bad_request,
                                           "malformed HTTP request: " + ec.message(), false);
                         }
                         return;
                       }
                       self->handle(self->parser_->release());
                     });
  }

  // Any failure nobody foresaw answers 500 and leaves the server (and this connection) up.
  void handle(http::request<http::string_body> request) {
    const unsigned version = request.version();
    const bool keep_alive = request.keep_alive();
    try {
      route(std::move(request));
    } catch (const std::exception& e) {
      spdlog::error("internal error answering a request: {}", e.what());
      sendError(http::status::internal_server_error, std::string("internal error: ") + e.what(),
                keep_alive, version);
    }
  }

  void route(http::request<http::string_body> request) {
    const std::string_view target(request.target().data(), request.target().size());
    const std::string method(request.method_string());
    // The viewer's files and /healthz are public; maps, poses and metrics need a token of
    // either role, changes an operator's. A WebSocket may also bring its token in its hello
    // message (browsers cannot set headers).
    const core::Grant grant = hub_.options.access.grant(tokenFrom(request));
    const bool token_given = grant.role != core::Role::kNone;
    if (core::needsToken(target) && !token_given) {
      return sendError(http::status::unauthorized,
                       "a valid token is required (Authorization: Bearer T or ?token=T)",
                       request.keep_alive());
    }
    if (websocket::is_upgrade(request)) return upgrade(request, target, token_given);
    if (auto session = mcapSession(target)) return streamMcap(*session, request);
    if (core::isAdminRequest(method, target)) {
      if (grant.role != core::Role::kOperator) {
        spdlog::warn("refused {} {}: the token '{}' is a viewer's", method,
                     common::printable(target.substr(0, 200)), grant.name);
        return sendError(http::status::forbidden,
                         "this token ('" + grant.name +
                             "') is a viewer's: opening, closing, deleting, merging and "
                             "importing sessions need an operator's",
                         request.keep_alive());
      }
      spdlog::info("{} {} by '{}' ({})", method, common::printable(target.substr(0, 200)),
                   grant.name, core::roleName(grant.role));
      const bool queued =
          hub_.admin_worker.post([self = shared_from_this(), method, target = std::string(target),
                                  body = std::move(request.body()), version = request.version(),
                                  keep_alive = request.keep_alive()] {
            core::HttpAnswer answer;
            try {
              answer = core::answerAdmin(self->hub_.admin, self->hub_.server, method, target, body);
            } catch (const std::exception& e) {
              spdlog::error("internal error in {} {}: {}", method, target.substr(0, 200), e.what());
              answer = {500, "application/json",
                        errorBody(std::string("internal error: ") + e.what()), ""};
            }
            asio::post(self->stream_.get_executor(),
                       [self, answer = std::move(answer), version, keep_alive]() mutable {
                         self->sendAnswer(std::move(answer), version, false, keep_alive);
                       });
          });
      if (!queued) {
        return sendError(http::status::service_unavailable,
                         std::to_string(AdminWorker::kMaxWaiting) +
                             " session-management requests are waiting already; try again later",
                         request.keep_alive());
      }
      return;
    }
    const auto header = request[http::field::if_none_match];
    const std::string_view if_none_match(header.data(), header.size());
    if (auto answer = core::answerApi(hub_.server, hub_.admin, method, target, if_none_match)) {
      return sendAnswer(std::move(*answer), request.version(), request.method() == http::verb::head,
                        request.keep_alive());
    }
    if (request.method() != http::verb::get && request.method() != http::verb::head) {
      return sendError(http::status::method_not_allowed, "only GET is supported",
                       request.keep_alive());
    }
    const ViewerFiles::File* file = hub_.files.find(target);
    if (file == nullptr) {
      if (hub_.files.size() == 0) {
        return sendError(http::status::not_found,
                         "the viewer is not built (nothing in " + hub_.files.root().string() +
                             "): run ./scripts/build or pass --web-root",
                         request.keep_alive());
      }
      return sendError(http::status::not_found,
                       "no viewer file " + std::string(target.substr(0, 200)),
                       request.keep_alive());
    }
    auto response =
        std::make_shared<http::response<http::string_body>>(http::status::ok, request.version());
    response->set(http::field::content_type, file->content_type);
    const bool head = request.method() == http::verb::head;
    if (!head) response->body() = file->content;
    write(response, request.keep_alive(),
          head ? std::optional(file->content.size()) : std::nullopt);
  }

  // Foxglove's protocol for a client that offers it (at / or /foxglove, ?session=ID for one
  // session's channels; the token is needed at the upgrade: Foxglove has no hello), else ours
  // at /ws.
  void upgrade(const http::request<http::string_body>& request, std::string_view target,
               bool token_given) {
    const std::string_view path = target.substr(0, target.find('?'));
    const std::string offered(request[http::field::sec_websocket_protocol]);
    std::string chosen;
    for (const char* protocol : {"foxglove.websocket.v1", "foxglove.sdk.v1"}) {
      if (chosen.empty() && common::listsToken(offered, protocol)) chosen = protocol;
    }
    if (chosen.empty()) {
      if (path != "/ws") {
        return sendError(http::status::not_found,
                         "the WebSocket endpoints are /ws (the viewer's protocol) and / or "
                         "/foxglove (Foxglove's, subprotocol foxglove.websocket.v1)",
                         false);
      }
      stream_.expires_never();
      std::make_shared<WebSocketSession>(stream_.release_socket(), hub_, hub_.viewers, "")
          ->start(request, [hub = &hub_, token_given] {
            return hub->viewers.connect(token_given, common::nowNs());
          });
      return;
    }
    if (path != "/" && path != "/foxglove") {
      return sendError(http::status::not_found,
                       "Foxglove's WebSocket endpoint is / or /foxglove (?session=ID for one)",
                       false);
    }
    if (!token_given) {
      return sendError(http::status::unauthorized,
                       "a valid token is required (?token=T or Authorization: Bearer T)", false);
    }
    const std::string session = common::queryParameter(target, "session").value_or("");
    if (!session.empty() && !core::isValidId(session)) {
      return sendError(http::status::bad_request, "session must be a session id", false);
    }
    stream_.expires_never();
    std::make_shared<WebSocketSession>(stream_.release_socket(), hub_, hub_.foxglove, chosen)
        ->start(request,
                [hub = &hub_, session] { return hub->foxglove.connect(session, common::nowNs()); });
  }

  // The session of /api/sessions/{id}/session.mcap (a query is allowed), else nullopt.
  static std::optional<std::string> mcapSession(std::string_view target) {
    const std::string_view path = target.substr(0, target.find('?'));
    constexpr std::string_view kPrefix = "/api/sessions/", kSuffix = "/session.mcap";
    if (path.size() <= kPrefix.size() + kSuffix.size() || !path.starts_with(kPrefix) ||
        !path.ends_with(kSuffix)) {
      return std::nullopt;
    }
    return std::string(path.substr(kPrefix.size(), path.size() - kPrefix.size() - kSuffix.size()));
  }

  // The export runs on a download thread that takes this connection's socket.
  void streamMcap(const std::string& session, const http::request<http::string_body>& request) {
    if (request.method() != http::verb::get) {
      return sendError(http::status::method_not_allowed, "session.mcap is fetched with GET",
                       request.keep_alive());
    }
    if (!hub_.options.session_mcap) {
      return sendError(http::status::not_implemented, "this server does not export MCAP",
                       request.keep_alive());
    }
    if (!core::isValidId(session)) {
      return sendError(http::status::bad_request, "not a session id", request.keep_alive());
    }
    stream_.expires_never();
    beast::error_code ec;
    const int fd = stream_.release_socket().release(ec);
    if (ec) return;
    auto export_mcap = hub_.options.session_mcap;
    const bool started = hub_.downloads.start(
        fd, "application/octet-stream", session + ".mcap",
        [export_mcap, session](const std::function<bool(std::string_view)>& sink) {
          return export_mcap(session, sink);
        });
    if (!started) {
      refuseDownload(fd, 503,
                     std::to_string(StreamedDownloads::kMaxRunning) +
                         " MCAP exports are under way already; try again later");
    }
  }

  void sendAnswer(core::HttpAnswer answer, unsigned version, bool head, bool keep_alive) {
    auto response = std::make_shared<http::response<http::string_body>>(
        static_cast<http::status>(answer.status), version);
    if (!answer.content_type.empty()) response->set(http::field::content_type, answer.content_type);
    if (answer.etag.empty()) {
      response->set(http::field::cache_control, "no-store");
    } else if (answer.immutable) {  // a versioned tile: never changes at its URL
      response->set(http::field::etag, answer.etag);
      response->set(http::field::cache_control, "public, max-age=31536000, immutable");
    } else {  // tiles: any cache may keep them, asking whether they are still current
      response->set(http::field::etag, answer.etag);
      response->set(http::field::cache_control, "no-cache");
    }
    for (const auto& [name, value] : answer.headers) response->set(name, value);
    if (!answer.filename.empty()) {
      response->set(http::field::content_disposition,
                    "inline; filename=\"" + answer.filename + "\"");
    }
    const size_t length = answer.body.size();
    if (!head) response->body() = std::move(answer.body);
    write(response, keep_alive, head ? std::optional(length) : std::nullopt);
  }

  void sendError(http::status status, const std::string& message, bool keep_alive,
                 unsigned version = 11) {
    auto response = std::make_shared<http::response<http::string_body>>(status, version);
    response->set(http::field::content_type, "application/json");
    response->body() = errorBody(message);
    write(response, keep_alive);
  }

  // `head_length`: the answer to HEAD states the length GET would have, with no body.
  void write(const std::shared_ptr<http::response<http::string_body>>& response, bool keep_alive,
             std::optional<size_t> head_length = std::nullopt) {
    response->set(http::field::server, "stereomap");
    response->keep_alive(keep_alive);
    response->prepare_payload();
    if (head_length) response->content_length(*head_length);
    // The timer armed at the request's read may have run out meanwhile (a site's alignments
    // take minutes on the admin worker); the answer gets a whole timeout of its own.
    stream_.expires_after(kIdleTimeout);
    http::async_write(
        stream_, *response,
        [self = shared_from_this(), response, keep_alive](beast::error_code ec, size_t) {
          if (ec) return;
          if (!keep_alive) return self->closeWrite();
          self->read();
        });
  }

  void closeWrite() {
    beast::error_code ignored;
    stream_.socket().shutdown(tcp::socket::shutdown_send, ignored);
  }

  beast::tcp_stream stream_;
  Hub& hub_;
  beast::flat_buffer buffer_;
  std::optional<http::request_parser<http::string_body>> parser_;
};

struct HttpServer::Impl {
  Impl(const HttpServerOptions& options, const core::MapServer& server, core::SessionAdmin* admin)
      : hub{server,
            admin,
            options,
            viewers::ViewerHub(server, admin,
                               {.access = options.access,
                                .stuck_after = options.stuck_after,
                                .max_queued_bytes = options.max_queued_bytes,
                                .server_name = "stereomap 0.2.0"}),
            viewers::FoxgloveHub(server, {.stuck_after = options.stuck_after,
                                          .max_queued_bytes = options.max_queued_bytes,
                                          .server_name = "stereomap 0.2.0"}),
            {},
            {},
            {},
            {}},
        acceptor(io),
        timer(io) {}

  void accept() {
    acceptor.async_accept([this](beast::error_code ec, tcp::socket socket) {
      if (ec == asio::error::operation_aborted) return;
      if (!ec) {
        // Viewers get many small messages (statuses, tiles, markers): with Nagle's algorithm
        // one waits for the ACK of the one before, which the client delays (40 ms on Linux).
        // Measured: live tile markers' p95 26 -> 66 ms once session statuses grew by 40 bytes.
        beast::error_code ignored;
        socket.set_option(tcp::no_delay(true), ignored);
        std::make_shared<HttpSession>(std::move(socket), hub)->start();
      }
      accept();
    });
  }

  void schedulePush() {
    timer.expires_after(hub.options.push_interval);
    timer.async_wait([this](beast::error_code ec) {
      if (ec) return;
      hub.viewers.poll(common::nowNs());
      hub.foxglove.poll(common::nowNs());
      const auto connections = hub.connections;  // pump() may end a connection
      for (const auto& [id, connection] : connections) connection->pump();
      schedulePush();
    });
  }

  asio::io_context io;
  Hub hub;
  tcp::acceptor acceptor;
  asio::steady_timer timer;
  std::thread thread;
  bool stopped = false;
  std::unique_ptr<TlsFront> tls;  // started with the server when options.tls_cert is set
};

HttpServer::HttpServer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
HttpServer::~HttpServer() { stop(); }

common::Result<std::unique_ptr<HttpServer>> HttpServer::create(const HttpServerOptions& options,
                                                               const core::MapServer& server,
                                                               core::SessionAdmin* admin) {
  auto impl = std::make_unique<Impl>(options, server, admin);
  impl->hub.files = ViewerFiles::load(options.web_root);
  if (impl->hub.files.size() > 0) {
    spdlog::info("viewer files: {} ({} kB) from {}{}", impl->hub.files.size(),
                 impl->hub.files.bytes() / 1024, impl->hub.files.root().string(),
                 impl->hub.files.skipped() > 0
                     ? " (" + std::to_string(impl->hub.files.skipped()) +
                           " left out: links leaving the folder, unreadable or too large)"
                     : "");
  }
  // Behind TLS the plain server listens on loopback only (TlsFront checks options.address).
  const bool tls = !options.tls_cert.empty();
  if (auto listening =
          listenOn(impl->acceptor, tls ? "127.0.0.1" : options.address, tls ? 0 : options.port);
      !listening) {
    return listening.error();
  }
  if (tls) {
    auto front = TlsFront::start({.address = options.address,
                                  .port = options.port,
                                  .cert_file = options.tls_cert,
                                  .key_file = options.tls_key,
                                  .backend_port = impl->acceptor.local_endpoint().port()});
    if (!front) return front.error();
    impl->tls = std::move(front).value();
  }
  return std::unique_ptr<HttpServer>(new HttpServer(std::move(impl)));
}

void HttpServer::start() {
  impl_->accept();
  impl_->schedulePush();
  impl_->thread = std::thread([this] {
    // A handler that throws past its own catch would end io.run(): log it and serve on.
    for (;;) {
      try {
        impl_->io.run();
        return;
      } catch (const std::exception& e) {
        spdlog::error("internal error on the network thread: {}", e.what());
      }
    }
  });
}

void HttpServer::stop() {
  if (impl_->stopped) return;
  impl_->stopped = true;
  if (impl_->tls) impl_->tls->stop();
  impl_->hub.admin_worker.stop();
  impl_->hub.downloads.stop();
  asio::post(impl_->io, [this] {
    beast::error_code ignored;
    impl_->acceptor.close(ignored);
    impl_->timer.cancel();
    const auto connections = impl_->hub.connections;
    for (const auto& [id, connection] : connections) connection->finish();
    impl_->io.stop();
  });
  if (impl_->thread.joinable()) impl_->thread.join();
}

uint16_t HttpServer::port() const {
  return impl_->tls ? impl_->tls->port() : impl_->acceptor.local_endpoint().port();
}

const char* HttpServer::scheme() const { return impl_->tls ? "https" : "http"; }
const char* HttpServer::wsScheme() const { return impl_->tls ? "wss" : "ws"; }

size_t HttpServer::viewers() const { return impl_->hub.viewer_count; }

}  // namespace stereomap::net
