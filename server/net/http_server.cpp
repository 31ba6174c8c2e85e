#include <utility>  // before Boost.Asio: g++ 12 in C++20 needs std::exchange declared first

#include "server/net/http_server.hpp"

#include <spdlog/spdlog.h>
#include <boost/asio.hpp>
#include <boost/beast.hpp>
#include <nlohmann/json.hpp>

#include <atomic>
#include <condition_variable>
#include <deque>
#include <functional>
#include <mutex>
#include <set>
#include <thread>

#include "server/core/api.hpp"
#include "server/core/viewer_feed.hpp"
#include "server/net/url.hpp"
#include "server/net/viewer_files.hpp"

namespace stereomap::net {

namespace asio = boost::asio;
namespace beast = boost::beast;
namespace http = beast::http;
namespace websocket = beast::websocket;
using tcp = asio::ip::tcp;

namespace {

constexpr size_t kMaxRequestBodyBytes = 64 * 1024;
constexpr auto kIdleTimeout = std::chrono::seconds(60);

std::string tokenFrom(const http::request<http::string_body>& request) {
  const std::string auth(request[http::field::authorization]);
  if (auth.starts_with("Bearer ")) return auth.substr(7);
  const std::string_view target(request.target().data(), request.target().size());
  return queryParameter(target, "token").value_or("");
}

// Compares in time that depends only on the lengths, so the token cannot be guessed byte by
// byte from response times.
bool sameToken(const std::string& given, const std::string& expected) {
  unsigned char difference = given.size() == expected.size() ? 0 : 1;
  for (size_t i = 0; i < given.size(); ++i) {
    difference |= static_cast<unsigned char>(given[i] ^ expected[i % expected.size()]);
  }
  return difference == 0;
}

// JSON text of an error message that may carry bytes from a request (invalid UTF-8 is
// replaced rather than thrown).
std::string errorBody(const std::string& message) {
  return nlohmann::json{{"error", message}}.dump(-1, ' ', false,
                                                 nlohmann::json::error_handler_t::replace) +
         "\n";
}

// Runs session-management requests (a replay can take seconds) one at a time, off the
// network thread, so that viewers and REST reads never wait for them.
class AdminWorker {
 public:
  AdminWorker() : thread_([this] { run(); }) {}
  ~AdminWorker() { stop(); }
  void post(std::function<void()> job) {
    {
      std::lock_guard lock(mutex_);
      jobs_.push_back(std::move(job));
    }
    changed_.notify_one();
  }
  void stop() {  // finishes the job under way; drops the queued ones
    {
      std::lock_guard lock(mutex_);
      stopping_ = true;
      jobs_.clear();
    }
    changed_.notify_one();
    if (thread_.joinable()) thread_.join();
  }

 private:
  void run() {
    for (;;) {
      std::function<void()> job;
      {
        std::unique_lock lock(mutex_);
        changed_.wait(lock, [this] { return stopping_ || !jobs_.empty(); });
        if (stopping_) return;
        job = std::move(jobs_.front());
        jobs_.pop_front();
      }
      job();
    }
  }
  std::mutex mutex_;
  std::condition_variable changed_;
  std::deque<std::function<void()>> jobs_;
  bool stopping_ = false;
  std::thread thread_;
};

}  // namespace

class WebSocketSession;

// Shared by every connection; touched only on the io thread.
struct Hub {
  const core::MapServer& server;
  core::SessionAdmin* admin;  // may be null
  HttpServerOptions options;
  core::ViewerFeed feed;
  ViewerFiles viewer;
  std::set<std::shared_ptr<WebSocketSession>> viewers;
  std::atomic<size_t> viewer_count{0};
  AdminWorker admin_worker;
};

class WebSocketSession : public std::enable_shared_from_this<WebSocketSession> {
 public:
  WebSocketSession(tcp::socket socket, Hub& hub) : ws_(std::move(socket)), hub_(hub) {}

  void start(http::request<http::string_body> request) {
    ws_.set_option(websocket::stream_base::timeout::suggested(beast::role_type::server));
    ws_.read_message_max(kMaxRequestBodyBytes);
    ws_.async_accept(request, [self = shared_from_this()](beast::error_code ec) {
      if (ec) return;
      self->hub_.viewers.insert(self);
      self->hub_.viewer_count = self->hub_.viewers.size();
      for (auto& message : self->hub_.feed.welcome())
        self->send(std::make_shared<std::string>(message));
      self->read();
    });
  }

  void send(std::shared_ptr<const std::string> message) {
    if (closed_) return;
    if (queue_.size() >= hub_.options.max_queued_messages) {
      spdlog::warn("viewer too slow ({} messages queued); disconnecting it", queue_.size());
      close();
      return;
    }
    queue_.push_back(std::move(message));
    if (queue_.size() == 1) writeNext();
  }

  void close() {
    if (closed_) return;
    closed_ = true;
    hub_.viewers.erase(shared_from_this());
    hub_.viewer_count = hub_.viewers.size();
    beast::error_code ignored;
    beast::get_lowest_layer(ws_).socket().shutdown(tcp::socket::shutdown_both, ignored);
    beast::get_lowest_layer(ws_).socket().close(ignored);
  }

 private:
  void writeNext() {
    ws_.text(true);
    ws_.async_write(asio::buffer(*queue_.front()),
                    [self = shared_from_this()](beast::error_code ec, size_t) {
                      if (ec) return self->close();
                      self->queue_.pop_front();
                      if (!self->queue_.empty()) self->writeNext();
                    });
  }

  void read() {
    ws_.async_read(buffer_, [self = shared_from_this()](beast::error_code ec, size_t) {
      if (ec) return self->close();
      // Viewers need not send anything; answer what we do not understand, keep the line.
      const std::string text = beast::buffers_to_string(self->buffer_.data());
      self->buffer_.consume(self->buffer_.size());
      nlohmann::json reply = {{"type", "error"},
                              {"message", "the server accepts no messages on /ws (got " +
                                              std::to_string(text.size()) + " bytes)"}};
      self->send(std::make_shared<std::string>(reply.dump()));
      self->read();
    });
  }

  websocket::stream<beast::tcp_stream> ws_;
  Hub& hub_;
  beast::flat_buffer buffer_;
  std::deque<std::shared_ptr<const std::string>> queue_;
  bool closed_ = false;
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
    // The viewer's files and /healthz are public; maps, poses and metrics need the token.
    const bool is_data = websocket::is_upgrade(request) || core::needsToken(target);
    if (is_data && !hub_.options.token.empty() &&
        !sameToken(tokenFrom(request), hub_.options.token)) {
      return sendError(http::status::unauthorized,
                       "a valid token is required (Authorization: Bearer T or ?token=T)",
                       request.keep_alive());
    }
    if (websocket::is_upgrade(request)) {
      if (target.substr(0, target.find('?')) != "/ws") {
        return sendError(http::status::not_found, "the WebSocket endpoint is /ws", false);
      }
      stream_.expires_never();
      std::make_shared<WebSocketSession>(stream_.release_socket(), hub_)->start(std::move(request));
      return;
    }
    if (core::isAdminRequest(method, target)) {
      hub_.admin_worker.post([self = shared_from_this(), method, target = std::string(target),
                              body = std::move(request.body()), version = request.version(),
                              keep_alive = request.keep_alive()] {
        core::HttpAnswer answer;
        try {
          answer = core::answerAdmin(self->hub_.admin, self->hub_.server, method, target, body);
        } catch (const std::exception& e) {
          spdlog::error("internal error in {} {}: {}", method, target.substr(0, 200), e.what());
          answer = {500, "application/json", errorBody(std::string("internal error: ") + e.what()),
                    ""};
        }
        asio::post(self->stream_.get_executor(),
                   [self, answer = std::move(answer), version, keep_alive]() mutable {
                     self->sendAnswer(std::move(answer), version, false, keep_alive);
                   });
      });
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
    const ViewerFiles::File* file = hub_.viewer.find(target);
    if (file == nullptr) {
      if (hub_.viewer.size() == 0) {
        return sendError(http::status::not_found,
                         "the viewer is not built (nothing in " + hub_.viewer.root().string() +
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
    write(response, request.keep_alive(), head ? std::optional(file->content.size()) : std::nullopt);
  }

  void sendAnswer(core::HttpAnswer answer, unsigned version, bool head, bool keep_alive) {
    auto response = std::make_shared<http::response<http::string_body>>(
        static_cast<http::status>(answer.status), version);
    if (!answer.content_type.empty()) response->set(http::field::content_type, answer.content_type);
    if (answer.etag.empty()) {
      response->set(http::field::cache_control, "no-store");
    } else {  // tiles: any cache may keep them, asking whether they are still current
      response->set(http::field::etag, answer.etag);
      response->set(http::field::cache_control, "no-cache");
    }
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
  void write(std::shared_ptr<http::response<http::string_body>> response, bool keep_alive,
             std::optional<size_t> head_length = std::nullopt) {
    response->set(http::field::server, "stereomap");
    response->keep_alive(keep_alive);
    response->prepare_payload();
    if (head_length) response->content_length(*head_length);
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
      : hub{server, admin, options, core::ViewerFeed(server), {}, {}, {}, {}},
        acceptor(io),
        timer(io) {}

  void accept() {
    acceptor.async_accept([this](beast::error_code ec, tcp::socket socket) {
      if (ec == asio::error::operation_aborted) return;
      if (!ec) std::make_shared<HttpSession>(std::move(socket), hub)->start();
      accept();
    });
  }

  void schedulePush() {
    timer.expires_after(hub.options.push_interval);
    timer.async_wait([this](beast::error_code ec) {
      if (ec) return;
      const auto messages = hub.feed.poll();
      if (!messages.empty() && !hub.viewers.empty()) {
        const auto viewers = hub.viewers;  // send() may disconnect a viewer
        for (const auto& text : messages) {
          auto shared = std::make_shared<const std::string>(text);
          for (const auto& viewer : viewers) viewer->send(shared);
        }
      }
      schedulePush();
    });
  }

  asio::io_context io;
  Hub hub;
  tcp::acceptor acceptor;
  asio::steady_timer timer;
  std::thread thread;
  bool stopped = false;
};

HttpServer::HttpServer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
HttpServer::~HttpServer() { stop(); }

common::Result<std::unique_ptr<HttpServer>> HttpServer::create(const HttpServerOptions& options,
                                                               const core::MapServer& server,
                                                               core::SessionAdmin* admin) {
  auto impl = std::make_unique<Impl>(options, server, admin);
  impl->hub.viewer = ViewerFiles::load(options.web_root);
  if (impl->hub.viewer.size() > 0) {
    spdlog::info("viewer files: {} ({} kB) from {}{}", impl->hub.viewer.size(),
                 impl->hub.viewer.bytes() / 1024, impl->hub.viewer.root().string(),
                 impl->hub.viewer.skipped() > 0
                     ? " (" + std::to_string(impl->hub.viewer.skipped()) +
                           " left out: links leaving the folder, unreadable or too large)"
                     : "");
  }
  beast::error_code ec;
  const auto address = asio::ip::make_address(options.address, ec);
  if (ec) {
    return common::makeError(common::ErrorCode::kInvalidArgument,
                             "'" + options.address + "' is not an IP address");
  }
  const tcp::endpoint endpoint(address, options.port);
  impl->acceptor.open(endpoint.protocol(), ec);
  if (!ec) impl->acceptor.set_option(asio::socket_base::reuse_address(true), ec);
  if (!ec) impl->acceptor.bind(endpoint, ec);
  if (!ec) impl->acceptor.listen(asio::socket_base::max_listen_connections, ec);
  if (ec) {
    return common::makeError(common::ErrorCode::kUnavailable,
                             "cannot listen on " + options.address + ":" +
                                 std::to_string(options.port) + ": " + ec.message());
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
  impl_->hub.admin_worker.stop();
  asio::post(impl_->io, [this] {
    beast::error_code ignored;
    impl_->acceptor.close(ignored);
    impl_->timer.cancel();
    const auto viewers = impl_->hub.viewers;
    for (const auto& viewer : viewers) viewer->close();
    impl_->io.stop();
  });
  if (impl_->thread.joinable()) impl_->thread.join();
}

uint16_t HttpServer::port() const { return impl_->acceptor.local_endpoint().port(); }

size_t HttpServer::viewers() const { return impl_->hub.viewer_count; }

}  // namespace stereomap::net
