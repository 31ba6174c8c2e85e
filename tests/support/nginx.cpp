#include "tests/support/nginx.hpp"

#include <pwd.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <sstream>

#include "tests/support/postgres.hpp"

namespace stereomap::testing {

namespace fs = std::filesystem;

namespace {

std::string replaced(std::string text, const std::string& from, const std::string& to) {
  for (size_t at = text.find(from); at != std::string::npos; at = text.find(from, at + to.size())) {
    text.replace(at, from.size(), to);
  }
  return text;
}

}  // namespace

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
  const std::string conf = nginx->prefix_ + "/nginx.conf";
  std::ofstream(conf) << config;
  const bool root = ::geteuid() == 0;
  if (root) {
    const passwd* nobody = ::getpwnam("nobody");
    std::error_code ec;
    if (nobody == nullptr || ::chown(nginx->prefix_.c_str(), nobody->pw_uid, nobody->pw_gid) != 0) {
      if (why) *why = "cannot hand " + nginx->prefix_ + " to the user nobody";
      return nullptr;
    }
  }
  std::vector<std::string> argv = {
      binary, "-p",         nginx->prefix_, "-c", conf, "-e", nginx->prefix_ + "/error.log",
      "-g",   "daemon off;"};
  if (root) {
    argv.insert(argv.begin(),
                {"/usr/bin/setpriv", "--reuid=nobody", "--regid=nogroup", "--clear-groups"});
  }
  nginx->process_ = std::make_unique<ChildProcess>(argv, nginx->prefix_ + "/stdout.log");
  const bool up = waitUntil(
      std::chrono::seconds(10),
      [&] {
        return !nginx->process_->running() || httpGet(nginx->port_, "/_nginx_probe").status != 0;
      },
      std::chrono::milliseconds(50));
  if (!up || !nginx->process_->running()) {
    std::ifstream log(nginx->prefix_ + "/error.log");
    std::stringstream errors;
    errors << log.rdbuf();
    if (why) *why = "nginx did not start: " + errors.str();
    return nullptr;
  }
  return nginx;
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
