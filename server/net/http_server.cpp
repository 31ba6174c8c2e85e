#include <utility>  // before Boost.Asio: g++ 12 in C++20 needs std::exchange declared first

#include "server/net/http_server.hpp"

#include <spdlog/spdlog.h>
#include <boost/asio.hpp>
#include <boost/beast.hpp>
#include <nlohmann/json.hpp>

#include <atomic>
#include <condition_variable>
#include <functional>
#include <mutex>
#include <deque>
#include <fstream>
#include <set>
#include <thread>

#include "server/core/api.hpp"
#include "server/core/viewer_feed.hpp"

namespace stereomap::net {

namespace asio = boost::asio;
namespace beast = boost::beast;
namespace http = beast::http;
namespace websocket = beast::websocket;
using tcp = asio::ip::tcp;

namespace {

constexpr size_t kMaxRequestBodyBytes = 64 * 1024;
constexpr auto kIdleTimeout = std::chrono::seconds(60);

std::string_view mimeType(const std::filesystem::path& path) {
  const std::string ext = path.extension().string();
  if (ext == ".html") return "text/html; charset=utf-8";
  if (ext == ".js" || ext == ".mjs") return "text/javascript; charset=utf-8";
  if (ext == ".css") return "text/css; charset=utf-8";
  if (ext == ".json" || ext == ".map") return "application/json";
  if (ext == ".svg") return "image/svg+xml";
  if (ext == ".png") return "image/png";
  if (ext == ".ico") return "image/x-icon";
  if (ext == ".wasm") return "application/wasm";
  return "application/octet-stream";
}

// The viewer file for a URL path, or an empty path when it is outside the web root.
std::filesystem::path staticFile(const std::filesystem::path& root, std::string_view target) {
  std::string path(target.substr(0, target.find_first_of("?#")));
  if (path.empty() || path.back() == '/') path += "index.html";
  for (size_t start = 0; start < path.size();) {  // refuse any ".." segment
    const size_t end = std::min(path.find('/', start), path.size());
    if (path.compare(start, end - start, "..") == 0) return {};
    start = end + 1;
  }
  if (path.find('\0') != std::string::npos || path.find('\\') != std::string::npos) return {};
  return root / path.substr(1);
}

bool readFile(const std::filesystem::path& path, std::string& out) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) return false;
  std::ifstream in(path, std::ios::binary);
  if (!in) return false;
  out.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  return true;
}

std::string tokenFrom(const http::request<http::string_body>& request) {
  const std::string auth(request[http::field::authorization]);
  if (auth.starts_with("Bearer ")) return auth.substr(7);
  const std::string_view target(request.target().data(), request.target().size());
  const size_t at = target.find("token=");
  if (at == std::string_view::npos || (at > 0 && target[at - 1] != '?' && target[at - 1] != '&')) {
    return "";
  }
  const std::string_view rest = target.substr(at + 6);
  return std::string(rest.substr(0, rest.find('&')));
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

  void handle(http::request<http::string_body> request) {
    const std::string_view target(request.target().data(), request.target().size());
    const std::string method(request.method_string());
    // The viewer's files are public; maps, poses and metrics need the token when one is set.
    const bool is_data = websocket::is_upgrade(request) || core::isApiPath(target);
    if (is_data && !hub_.options.token.empty() && tokenFrom(request) != hub_.options.token) {
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
        auto answer = core::answerAdmin(self->hub_.admin, self->hub_.server, method, target, body);
        asio::post(self->stream_.get_executor(),
                   [self, answer = std::move(answer), version, keep_alive]() mutable {
                     self->sendAnswer(std::move(answer), version, false, keep_alive);
                   });
      });
      return;
    }
    if (auto answer = core::answerApi(hub_.server, hub_.admin, method, target)) {
      return sendAnswer(std::move(*answer), request.version(),
                        request.method() == http::verb::head, request.keep_alive());
    }
    if (request.method() != http::verb::get && request.method() != http::verb::head) {
      return sendError(http::status::method_not_allowed, "only GET is supported",
                       request.keep_alive());
    }
    const auto path = staticFile(hub_.options.web_root, target);
    std::string body;
    if (path.empty()) {
      return sendError(http::status::bad_request, "path leaves the viewer's folder",
                       request.keep_alive());
    }
    if (!readFile(path, body)) {
      if (path.filename() == "index.html") {
        return sendError(http::status::not_found,
                         "the viewer is not built (no " + path.string() +
                             "): run ./scripts/build or pass --web-root",
                         request.keep_alive());
      }
      return sendError(http::status::not_found, "no file " + std::string(target),
                       request.keep_alive());
    }
    auto response =
        std::make_shared<http::response<http::string_body>>(http::status::ok, request.version());
    response->set(http::field::content_type, std::string(mimeType(path)));
    response->body() = request.method() == http::verb::head ? "" : std::move(body);
    write(response, request.keep_alive());
  }

  void sendAnswer(core::HttpAnswer answer, unsigned version, bool head, bool keep_alive) {
    auto response = std::make_shared<http::response<http::string_body>>(
        static_cast<http::status>(answer.status), version);
    response->set(http::field::content_type, answer.content_type);
    response->set(http::field::cache_control, "no-store");
    if (!answer.filename.empty()) {
      response->set(http::field::content_disposition,
                    "inline; filename=\"" + answer.filename + "\"");
    }
    response->body() = head ? "" : std::move(answer.body);
    write(response, keep_alive);
  }

  void sendError(http::status status, const std::string& message, bool keep_alive) {
    auto response = std::make_shared<http::response<http::string_body>>(status, 11);
    response->set(http::field::content_type, "application/json");
    response->body() = nlohmann::json{{"error", message}}.dump() + "\n";
    write(response, keep_alive);
  }

  void write(std::shared_ptr<http::response<http::string_body>> response, bool keep_alive) {
    response->set(http::field::server, "stereomap");
    response->keep_alive(keep_alive);
    response->prepare_payload();
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
      : hub{server, admin, options, core::ViewerFeed(server), {}, {}, {}}, acceptor(io), timer(io) {}

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
  impl_->thread = std::thread([this] { impl_->io.run(); });
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
