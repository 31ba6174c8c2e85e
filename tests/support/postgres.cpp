#include "tests/support/postgres.hpp"

#include <netinet/in.h>
#include <pwd.h>
#include <signal.h>
#include <sys/socket.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <random>
#include <thread>
#include <vector>

#include <cstdio>

namespace stereomap::testing {

namespace fs = std::filesystem;

std::string postgresBinDir() {
  std::string best;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator("/usr/lib/postgresql", ec)) {
    const fs::path bin = entry.path() / "bin";
    if (fs::exists(bin / "postgres", ec) && fs::exists(bin / "initdb", ec) && bin.string() > best) {
      best = bin.string();
    }
  }
  return best;
}

std::string randomPassword() {
  static const char kLetters[] = "abcdefghijkmnopqrstuvwxyzABCDEFGHJKLMNPQRSTUVWXYZ23456789";
  std::random_device random;
  std::string out;
  for (int i = 0; i < 24; ++i) out += kLetters[random() % (sizeof(kLetters) - 1)];
  return out;
}

std::string logTail(const std::string& path) {
  std::ifstream in(path);
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  return text.size() > 2000 ? text.substr(text.size() - 2000) : text;
}

std::vector<std::string> asUnprivileged(std::vector<std::string> argv) {
  if (::geteuid() != 0) return argv;
  std::vector<std::string> wrapped = {"/usr/bin/setpriv", "--reuid=nobody", "--regid=nogroup",
                                      "--clear-groups"};
  wrapped.insert(wrapped.end(), argv.begin(), argv.end());
  return wrapped;
}

bool handToUnprivileged(const std::string& dir) {
  if (::geteuid() != 0) return true;
  const passwd* nobody = ::getpwnam("nobody");
  return nobody != nullptr && ::chown(dir.c_str(), nobody->pw_uid, nobody->pw_gid) == 0;
}

int unusedPort() {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  address.sin_port = 0;
  socklen_t length = sizeof(address);
  int port = 0;
  if (::bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)) == 0 &&
      ::getsockname(fd, reinterpret_cast<sockaddr*>(&address), &length) == 0) {
    port = ntohs(address.sin_port);
  }
  ::close(fd);
  return port;
}

std::unique_ptr<TestPostgres> TestPostgres::start(std::string* why) {
  auto db = std::unique_ptr<TestPostgres>(new TestPostgres);
  db->bin_ = postgresBinDir();
  if (db->bin_.empty()) {
    if (why) *why = "PostgreSQL is not installed (no /usr/lib/postgresql/*/bin/postgres)";
    return nullptr;
  }
  db->dir_ = makeTempDir("stereomap-pg");
  db->password_ = randomPassword();
  if (!handToUnprivileged(db->dir_)) {
    if (why) *why = "cannot hand " + db->dir_ + " to the user nobody";
    return nullptr;
  }
  {
    std::ofstream pw(db->dir_ + "/password");
    pw << db->password_ << "\n";
  }
  const auto init =
      runTool(asUnprivileged({db->bin_ + "/initdb", "-D", db->dir_ + "/data", "-U", "stereomap",
                              "--pwfile=" + db->dir_ + "/password", "--auth=scram-sha-256", "-E",
                              "UTF8", "--no-instructions", "--no-sync"}));
  fs::remove(db->dir_ + "/password");
  if (init.exit_code != 0) {
    if (why) *why = "initdb failed: " + init.output;
    return nullptr;
  }
  db->port_ = unusedPort();
  if (!db->launch(why)) return nullptr;
  return db;
}

bool TestPostgres::launch(std::string* why) {
  const std::string log = dir_ + "/postgres.log";
  postmaster_ = std::make_unique<ChildProcess>(
      asUnprivileged({bin_ + "/postgres", "-D", dir_ + "/data", "-p", std::to_string(port_), "-c",
                      "listen_addresses=127.0.0.1", "-c", "unix_socket_directories=" + dir_, "-c",
                      "max_connections=200", "-c", "shared_buffers=64MB"}),
      log);
  const bool ready = waitUntil(
      std::chrono::seconds(30),
      [&] {
        if (!postmaster_->running()) return true;
        const auto probe =
            runTool({bin_ + "/pg_isready", "-q", "-h", "127.0.0.1", "-p", std::to_string(port_)},
                    std::chrono::seconds(10));
        return probe.exit_code == 0;
      },
      std::chrono::milliseconds(100));
  if (!ready || !postmaster_->running()) {
    if (why) *why = "PostgreSQL did not start; its log (" + log + "):\n" + logTail(log);
    return false;
  }
  return true;
}

TestPostgres::~TestPostgres() {
  if (postmaster_ && postmaster_->running()) stop();
  std::error_code ec;
  fs::remove_all(dir_, ec);
}

std::string TestPostgres::url(const std::string& database) const {
  return urlWithPassword(password_, database);
}

std::string TestPostgres::urlWithPassword(const std::string& password,
                                          const std::string& database) const {
  return "postgresql://stereomap:" + password + "@127.0.0.1:" + std::to_string(port_) + "/" +
         database;
}

std::optional<std::string> runPsql(const std::string& bin, const std::string& url,
                                   const std::string& statement) {
  const auto run = runTool(
      {bin + "/psql", "-X", "-q", "-t", "-A", "-v", "ON_ERROR_STOP=1", "-d", url, "-c", statement},
      std::chrono::seconds(60));
  if (run.exit_code != 0) return std::nullopt;
  return run.output;
}

std::optional<std::string> TestPostgres::sql(const std::string& statement,
                                             const std::string& database) {
  return runPsql(bin_, url(database), statement);
}

bool TestDatabase::createDatabase(const std::string& name, std::string* why) {
  if (sql("CREATE DATABASE \"" + name + "\"")) return true;
  if (why) *why = "cannot create database " + name;
  return false;
}

bool TestPostgres::running() { return postmaster_ && postmaster_->running(); }

void TestPostgres::stop() {
  // SIGINT: PostgreSQL's fast shutdown (SIGTERM waits for every client to leave).
  if (!running()) return;
  ::kill(postmaster_->pid(), SIGINT);
  if (!postmaster_->waitExit(std::chrono::seconds(30))) postmaster_->kill9();
}

void TestPostgres::kill9() {
  if (running()) postmaster_->kill9();
}

void TestPostgres::crash() {
  if (running()) killWithChildren(postmaster_->pid());
}

void TestPostgres::pause() {
  if (running()) signalWithChildren(postmaster_->pid(), SIGSTOP);
}

void TestPostgres::resume() {
  if (running()) signalWithChildren(postmaster_->pid(), SIGCONT);
}

bool TestPostgres::restart(std::string* why) {
  if (running()) stop();
  return launch(why);
}

}  // namespace stereomap::testing
