// A listening TCP socket for the HTTP server and its TLS front: the address parsed, the port
// bound (reused across restarts), each failure a clear error naming address and port.
#pragma once

#include <boost/asio.hpp>

#include <cstdint>
#include <string>

#include "common/result.hpp"

namespace stereomap::net {

inline common::Status listenOn(boost::asio::ip::tcp::acceptor& acceptor, const std::string& address,
                               uint16_t port) {
  namespace asio = boost::asio;
  boost::system::error_code ec;
  const auto ip = asio::ip::make_address(address, ec);
  if (ec) {
    return common::makeError(common::ErrorCode::kInvalidArgument,
                             "'" + address + "' is not an IP address");
  }
  const asio::ip::tcp::endpoint endpoint(ip, port);
  acceptor.open(endpoint.protocol(), ec);
  if (!ec) acceptor.set_option(asio::socket_base::reuse_address(true), ec);
  if (!ec) acceptor.bind(endpoint, ec);
  if (!ec) acceptor.listen(asio::socket_base::max_listen_connections, ec);
  if (ec) {
    return common::makeError(
        common::ErrorCode::kUnavailable,
        "cannot listen on " + address + ":" + std::to_string(port) + ": " + ec.message());
  }
  return common::Ok{};
}

}  // namespace stereomap::net
