// Fuzz target: an HTTP request as the server's port takes it: Beast's parser with the
// server's limits, then the REST router (server/core/api: /healthz, /metrics, /api/...,
// including the admin requests), then the viewer's file index. The input is the raw request.
// Every answer must be a valid status with a body that fits what was asked; ids and numbers
// reach the store only once valid (fuzz_server.hpp's admin checks), and no request path
// reaches the file system (the index never serves a file outside the built viewer).
#include <boost/beast/core/flat_buffer.hpp>
#include <boost/beast/http.hpp>
#include <string>

#include "common/url.hpp"
#include "server/core/api.hpp"
#include "server/net/viewer_files.hpp"
#include "tests/fuzz/fuzz_input.hpp"
#include "tests/fuzz/fuzz_server.hpp"

namespace {

namespace http = boost::beast::http;
using namespace stereomap;

const net::ViewerFiles& viewerFiles() {
  static const net::ViewerFiles files = [] {
    const auto& dir = fuzz::scratch();
    std::filesystem::create_directories(dir.path() / "web" / "assets");
    dir.write("web/index.html", "<html></html>");
    dir.write("web/assets/app.js", "// app");
    dir.write("secret.txt", "outside the viewer");
    return net::ViewerFiles::load(dir.path() / "web");
  }();
  return files;
}

void checkAnswer(const core::HttpAnswer& answer) {
  if (answer.status < 200 || answer.status > 599) __builtin_trap();
  if (answer.status == 304 && !answer.body.empty()) __builtin_trap();
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  auto& server = fuzz::fusedServer();
  static fuzz::IdCheckingAdmin admin;
  http::request_parser<http::string_body> parser;
  parser.body_limit(uint64_t{64} * 1024);  // http_server.cpp's kMaxRequestBodyBytes
  parser.eager(true);
  boost::beast::error_code ec;
  parser.put(boost::asio::buffer(data, size), ec);
  if (!ec && !parser.is_done()) parser.put_eof(ec);
  if (ec || !parser.is_done()) return 0;  // answered 400 by the server
  const auto& request = parser.get();
  const std::string_view target(request.target().data(), request.target().size());
  const std::string method(request.method_string());

  core::needsToken(target);
  common::queryParameter(target, "token");
  if (core::isAdminRequest(method, target)) {
    checkAnswer(core::answerAdmin(&admin, server, method, target, request.body()));
    return 0;
  }
  const auto header = request[http::field::if_none_match];
  if (auto answer =
          core::answerApi(server, &admin, method, target, {header.data(), header.size()})) {
    checkAnswer(*answer);
    return 0;
  }
  if (const auto* file = viewerFiles().find(target)) {
    if (file->content == "outside the viewer") __builtin_trap();
  }
  return 0;
}
