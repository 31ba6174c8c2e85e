#include "tests/support/nginx.hpp"

#include <filesystem>
#include <fstream>
#include <sstream>

#include "tests/support/postgres.hpp"

namespace stereomap::testing {

namespace fs = std::filesystem;

std::unique_ptr<TestNginx> TestNginx::start(const std::vector<std::string>& upstreams,
                                            std::string* why) {
  const std::string binary = "/usr/sbin/nginx";
  if (!fs::exists(binary)) {
    if (why) *why = "nginx is not installed (apt-get install nginx-light)";
    return nullptr;
  }
  auto nginx = std::unique_ptr<TestNginx>(new TestNginx);
  nginx->prefix_ = makeTempDir("stereomap-nginx");
  nginx->port_ = unusedPort();
  std::ifstream in(STEREOMAP_NGINX_TEMPLATE);
  std::stringstream text;
  text << in.rdbuf();
  std::string lines;
  for (const auto& upstream : upstreams) {
    lines += "    server " + upstream + " max_fails=1 fail_timeout=2s;\n";
  }
  std::string config = replaced(text.str(), "@PREFIX@", nginx->prefix_);
  config = replaced(config, "@LISTEN@", "127.0.0.1:" + std::to_string(nginx->port_));
  config = replaced(config, "@UPSTREAMS@", lines);
  config = replaced(config, "@RESOLVER@", "");
  config = replaced(config, "@TLS@", "");
  const std::string conf = nginx->prefix_ + "/nginx.conf";
  std::ofstream(conf) << config;
  if (!handToUnprivileged(nginx->prefix_)) {
    if (why) *why = "cannot hand " + nginx->prefix_ + " to the user nobody";
    return nullptr;
  }
  nginx->argv_ = asUnprivileged({binary, "-p", nginx->prefix_, "-c", conf, "-e",
                                 nginx->prefix_ + "/error.log", "-g", "daemon off;"});
  if (!nginx->launch(why)) return nullptr;
  return nginx;
}

bool TestNginx::launch(std::string* why) {
  process_ = std::make_unique<ChildProcess>(argv_, prefix_ + "/stdout.log");
  const bool up = waitUntil(
      std::chrono::seconds(10),
      [&] { return !process_->running() || httpGet(port_, "/_nginx_probe").status != 0; },
      std::chrono::milliseconds(50));
  if (!up || !process_->running()) {
    std::ifstream log(prefix_ + "/error.log");
    std::stringstream errors;
    errors << log.rdbuf();
    if (why) *why = "nginx did not start: " + errors.str();
    return false;
  }
  return true;
}

bool TestNginx::restart(std::string* why) {
  // Killed as a crash would: its workers too (they would hold the port).
  if (process_ && process_->running()) killWithChildren(process_->pid());
  process_.reset();
  return launch(why);
}

TestNginx::~TestNginx() {
  if (process_) process_->stop(std::chrono::seconds(5));
  std::error_code ec;
  fs::remove_all(prefix_, ec);
}

std::string TestNginx::accessLog() const {
  std::ifstream in(prefix_ + "/access.log");
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

}  // namespace stereomap::testing
