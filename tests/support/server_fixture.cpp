#include "tests/support/server_fixture.hpp"

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <stdexcept>

namespace stereomap::testing {

using namespace std::chrono_literals;

namespace {

// The loopback DDS configuration, unless the test chose one.
void withLoopbackDds(std::vector<std::string>& argv, const std::vector<std::string>& extra) {
  if (std::find(extra.begin(), extra.end(), "--dds-config") == extra.end()) {
    argv.insert(argv.end(), {"--dds-config", STEREOMAP_DDS_CONFIG});
  }
}

}  // namespace

ServerProcess::ServerProcess(int domain, const std::vector<std::string>& extra_args,
                             const std::string& store, bool require_healthy,
                             std::chrono::seconds start_within) {
  owns_store_ = store.empty();
  store_ = owns_store_ ? makeTempDir("stereomap-test-store") : store;
  log_ = makeTempDir("stereomap-test-log") + "/server.log";
  std::vector<std::string> argv = {std::string(STEREOMAP_BIN_DIR) + "/stereomap-server",
                                   "--http",
                                   "127.0.0.1:0",
                                   "--store",
                                   store_,
                                   "--domain",
                                   std::to_string(domain)};
  withLoopbackDds(argv, extra_args);
  argv.insert(argv.end(), extra_args.begin(), extra_args.end());
  process_ = std::make_unique<ChildProcess>(argv, log_);
  // The server logs "viewer: http://127.0.0.1:PORT/" once it listens.
  const bool up = waitUntil(start_within, [&] {
    const std::string text = log();
    const size_t at = text.find("viewer: http://127.0.0.1:");
    if (at == std::string::npos) return !process_->running();
    port_ = std::atoi(text.c_str() + at + 25);
    return true;
  });
  const int health = up && port_ != 0 ? httpGet(port_, "/healthz").status : 0;
  if (health == 0 || (require_healthy && health != 200)) {
    throw std::runtime_error("stereomap-server did not come up; its log:\n" + log());
  }
}

ServerProcess::~ServerProcess() {
  process_->stop();
  std::error_code ec;
  if (owns_store_) std::filesystem::remove_all(store_, ec);
  std::filesystem::remove_all(std::filesystem::path(log_).parent_path(), ec);
}

std::string ServerProcess::log() const {
  std::ifstream in(log_);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

std::vector<std::string> onboardArgs(int domain, const std::string& session, int frames,
                                     const std::vector<std::string>& extra) {
  std::vector<std::string> argv = {std::string(STEREOMAP_BIN_DIR) + "/stereomap-onboard",
                                   "--source",
                                   "sim",
                                   "--session",
                                   session,
                                   "--frames",
                                   std::to_string(frames),
                                   "--domain",
                                   std::to_string(domain)};
  withLoopbackDds(argv, extra);
  // Every cloud is sent whole and none is held back for a link's budget, so that tests can
  // count frames and fill disks at any map resolution; the tests of the link choose.
  for (const char* flag : {"--min-new", "--map-resolution", "--link-budget"}) {
    if (std::find(extra.begin(), extra.end(), flag) == extra.end()) {
      argv.insert(argv.end(), {flag, "0"});
    }
  }
  // Tests run side by side with the same vehicle id: none inherits another's spool folder. And
  // tests count frames: on a loaded machine the sim takes each one late instead of skipping.
  for (const auto& [flag, value] : {std::pair{"--spool", "memory"}, {"--skip-late", "off"}}) {
    if (std::find(extra.begin(), extra.end(), flag) == extra.end()) {
      argv.insert(argv.end(), {flag, value});
    }
  }
  argv.insert(argv.end(), extra.begin(), extra.end());
  return argv;
}

}  // namespace stereomap::testing
