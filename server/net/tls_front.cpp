#include <utility>  // before Boost.Asio: g++ 12 in C++20 needs std::exchange declared first

#include "server/net/tls_front.hpp"

#include "server/net/listen.hpp"

#include <spdlog/spdlog.h>
#include <boost/asio.hpp>
#include <boost/asio/ssl.hpp>

#include <array>
#include <atomic>
#include <thread>

namespace stereomap::net {

namespace asio = boost::asio;
namespace ssl = asio::ssl;
using tcp = asio::ip::tcp;
using error_code = boost::system::error_code;

namespace {

// One client: the TLS handshake (timed), a connection to the plain server, then bytes both
// ways until either side ends; then both are closed.
class Relay : public std::enable_shared_from_this<Relay> {
 public:
  Relay(tcp::socket socket, ssl::context& context, const TlsFrontOptions& options,
        std::atomic<size_t>& open)
      : client_(std::move(socket), context),
        backend_(client_.get_executor()),
        timer_(client_.get_executor()),
        options_(options),
        open_(open) {
    ++open_;
  }
  ~Relay() { --open_; }

  void start() {
    timer_.expires_after(options_.handshake_timeout);
    timer_.async_wait([self = shared_from_this()](error_code ec) {
      if (!ec && !self->handshaken_) self->close();
    });
    client_.async_handshake(ssl::stream_base::server, [self = shared_from_this()](error_code ec) {
      self->handshaken_ = true;
      self->timer_.cancel();
      if (ec) return self->close();
      self->connectBackend();
    });
  }

 private:
  void connectBackend() {
    const tcp::endpoint backend(asio::ip::make_address_v4("127.0.0.1"), options_.backend_port);
    backend_.async_connect(backend, [self = shared_from_this()](error_code ec) {
      if (ec) {
        spdlog::warn("tls: cannot reach the HTTP server on 127.0.0.1:{}: {}",
                     self->options_.backend_port, ec.message());
        return self->close();
      }
      error_code ignored;
      self->backend_.set_option(tcp::no_delay(true), ignored);
      self->clientToBackend();
      self->backendToClient();
    });
  }

  void clientToBackend() {
    client_.async_read_some(asio::buffer(up_), [self = shared_from_this()](error_code ec,
                                                                           size_t n) {
      if (ec) {
        // The client is done (close_notify or gone): the server sees the end of its request.
        error_code ignored;
        self->backend_.shutdown(tcp::socket::shutdown_send, ignored);
        return self->finished();
      }
      asio::async_write(self->backend_, asio::buffer(self->up_, n), [self](error_code ec, size_t) {
        if (ec) return self->close();
        self->clientToBackend();
      });
    });
  }

  void backendToClient() {
    backend_.async_read_some(asio::buffer(down_), [self = shared_from_this()](error_code ec,
                                                                              size_t n) {
      if (ec) return self->close();  // the server closed: so does the client's connection
      asio::async_write(self->client_, asio::buffer(self->down_, n), [self](error_code ec, size_t) {
        if (ec) return self->close();
        self->backendToClient();
      });
    });
  }

  void finished() {
    if (++directions_done_ == 2) close();
  }

  void close() {
    if (closed_) return;
    closed_ = true;
    error_code ignored;
    timer_.cancel();
    backend_.close(ignored);
    // No close_notify wait: the bytes are all written, and a client gone silent must not hold
    // the relay.
    client_.lowest_layer().shutdown(tcp::socket::shutdown_both, ignored);
    client_.lowest_layer().close(ignored);
  }

  ssl::stream<tcp::socket> client_;
  tcp::socket backend_;
  asio::steady_timer timer_;
  const TlsFrontOptions& options_;
  std::atomic<size_t>& open_;
  std::array<char, 16 * 1024> up_{};
  std::array<char, 64 * 1024> down_{};
  bool handshaken_ = false;
  bool closed_ = false;
  int directions_done_ = 0;
};

}  // namespace

struct TlsFront::Impl {
  explicit Impl(const TlsFrontOptions& options)
      : options(options), context(ssl::context::tls_server), acceptor(io) {}

  void accept() {
    acceptor.async_accept([this](error_code ec, tcp::socket socket) {
      if (ec == asio::error::operation_aborted) return;
      if (!ec) {
        if (open >= options.max_connections) {
          error_code ignored;
          socket.close(ignored);
        } else {
          error_code ignored;
          socket.set_option(tcp::no_delay(true), ignored);
          std::make_shared<Relay>(std::move(socket), context, options, open)->start();
        }
      }
      accept();
    });
  }

  // Declared before io: relays still queued when io goes use them in their destructors.
  TlsFrontOptions options;
  ssl::context context;
  std::atomic<size_t> open{0};
  asio::io_context io;
  tcp::acceptor acceptor;
  std::thread thread;
  bool stopped = false;
};

TlsFront::TlsFront(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
TlsFront::~TlsFront() { stop(); }

common::Result<std::unique_ptr<TlsFront>> TlsFront::start(const TlsFrontOptions& options) {
  auto impl = std::make_unique<Impl>(options);
  auto& context = impl->context;
  error_code ec;
  context.set_options(ssl::context::default_workarounds | ssl::context::no_sslv2 |
                          ssl::context::no_sslv3 | ssl::context::no_tlsv1 |
                          ssl::context::no_tlsv1_1 | ssl::context::single_dh_use,
                      ec);
  context.use_certificate_chain_file(options.cert_file, ec);
  if (ec) {
    return common::makeError(
        common::ErrorCode::kInvalidArgument,
        "--tls-cert " + options.cert_file + ": not a PEM certificate (chain): " + ec.message());
  }
  context.use_private_key_file(options.key_file, ssl::context::pem, ec);
  if (ec) {
    return common::makeError(
        common::ErrorCode::kInvalidArgument,
        "--tls-key " + options.key_file +
            ": not an unencrypted PEM key matching --tls-cert: " + ec.message());
  }
  if (auto listening = listenOn(impl->acceptor, options.address, options.port); !listening) {
    return listening.error();
  }
  impl->accept();
  auto* raw = impl.get();
  impl->thread = std::thread([raw] {
    for (;;) {
      try {
        raw->io.run();
        return;
      } catch (const std::exception& e) {
        spdlog::error("internal error on the TLS thread: {}", e.what());
      }
    }
  });
  return std::unique_ptr<TlsFront>(new TlsFront(std::move(impl)));
}

void TlsFront::stop() {
  if (impl_->stopped) return;
  impl_->stopped = true;
  asio::post(impl_->io, [this] {
    error_code ignored;
    impl_->acceptor.close(ignored);
    impl_->io.stop();
  });
  if (impl_->thread.joinable()) impl_->thread.join();
}

uint16_t TlsFront::port() const { return impl_->acceptor.local_endpoint().port(); }

}  // namespace stereomap::net
