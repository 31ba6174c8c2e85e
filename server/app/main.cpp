// stereomap-server: receives clouds and poses over DDS, fuses them into an occupancy map per
// session, keeps sessions on disk, and serves the viewer, the REST API and live pushes.
#include <spdlog/spdlog.h>
#include <CLI/CLI.hpp>

#include <cctype>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <optional>
#include <thread>
#include <tuple>
#include <vector>

#include "common/cli.hpp"
#include "common/shutdown.hpp"
#include "proto/dds_cli.hpp"
#include "server/app/run.hpp"
#include "server/core/map_server.hpp"
#include "server/fusion/octomap_log.hpp"
#include "server/ingest/dds_ingest.hpp"
#include "server/net/http_server.hpp"
#include "server/store/store_admin.hpp"

namespace {

using namespace stereomap;
using app::Flags;

// The token from --token, --token-file or $STEREOMAP_TOKEN (at most one of the flags);
// exits 2 with a message on a bad file. Empty: none.
std::optional<std::string> resolveToken(const std::string& flag, const std::string& file) {
  if (!flag.empty() && !file.empty()) {
    spdlog::error("pass either --token or --token-file, not both");
    return std::nullopt;
  }
  if (!flag.empty()) {
    spdlog::warn(
        "--token is visible to every local user in the process list; prefer "
        "--token-file FILE or the STEREOMAP_TOKEN environment variable");
    return flag;
  }
  if (!file.empty()) {
    std::ifstream in(file);
    std::string token;
    if (!in || !std::getline(in, token)) {
      spdlog::error("--token-file {}: cannot read a token from it", file);
      return std::nullopt;
    }
    while (!token.empty() && std::isspace(static_cast<unsigned char>(token.back())))
      token.pop_back();
    if (token.empty()) {
      spdlog::error("--token-file {}: the first line is empty", file);
      return std::nullopt;
    }
    return token;
  }
  const char* from_environment = std::getenv("STEREOMAP_TOKEN");
  std::string token = from_environment != nullptr ? from_environment : "";
  ::unsetenv("STEREOMAP_TOKEN");  // not handed on to anything this process starts
  return token;
}

bool isLoopback(const std::string& address) {
  return address == "127.0.0.1" || address == "::1" || address.rfind("127.", 0) == 0 ||
         address == "localhost";
}

void addFlags(CLI::App& app, Flags& f) {
  app.add_option("--http", f.http_spec,
                 "Address and port for HTTP and the WebSockets (the viewer's /ws, Foxglove's "
                 "/foxglove)")
      ->capture_default_str();
  app.add_option("--store", f.store_dir, "Directory where sessions are kept")
      ->capture_default_str();
  app.add_option("--resolution", f.options.resolution, "Finest voxel edge, metres")
      ->check(CLI::Range(0.01, 2.0))
      ->capture_default_str();
  proto::addDdsFlags(app, f.dds);
  app.add_option("--web-root", f.web_root, "The built viewer (default: ../web beside this binary)");
  app.add_option("--tokens", f.tokens_file,
                 "Access list: one token per line, 'viewer|operator sha256:HEX NAME' (made by "
                 "stereomap-certs token). Viewers read maps, /ws, Foxglove and exports; "
                 "operators also open, close, delete, merge, align and make sites. A token is "
                 "required when --http is not a loopback address")
      ->check(CLI::ExistingFile);
  app.add_option("--tls-cert", f.tls_cert,
                 "Serve https and wss with this PEM certificate (chain); needs --tls-key")
      ->check(CLI::ExistingFile);
  app.add_option("--tls-key", f.tls_key, "The --tls-cert's private key (PEM, unencrypted)")
      ->check(CLI::ExistingFile);
  app.add_flag("--insecure-http", f.insecure_http,
               "Serve plain HTTP on an address that is not loopback (only behind a proxy that "
               "terminates TLS, as the cluster's nginx does): tokens and maps cross the network "
               "in clear otherwise");
  app.add_option("--token-file", f.token_file,
                 "File whose first line is one operator's token (Authorization: Bearer T or "
                 "?token=T), named 'token'. Or set STEREOMAP_TOKEN in the environment");
  app.add_option("--token", f.token,
                 "The operator token itself (visible to every local user in the process list: "
                 "prefer --tokens, --token-file or STEREOMAP_TOKEN)");
  app.add_option("--max-cloud-bytes", f.options.limits.max_payload_bytes,
                 "Largest accepted cloud payload, bytes")
      ->check(CLI::Range(size_t{1024}, proto::kMaxPayloadBytes))
      ->capture_default_str();
  app.add_option("--snapshot-every", f.options.snapshot_every,
                 "Fused frames between map snapshots (recovery replays only the journal after "
                 "the last one)")
      ->check(CLI::Range(1, 1000000))
      ->capture_default_str();
  app.add_option("--snapshot-interval", f.snapshot_interval_s,
                 "Least seconds between a session's snapshots (default: none on a single server; "
                 "30 in a cluster, where each snapshot is megabytes of database writes that "
                 "samples' commits wait behind)")
      ->check(CLI::Range(0.0, 86400.0));
  app.add_option("--vehicle-timeout", f.vehicle_timeout_s,
                 "Seconds without samples after which a live session counts as ended (its "
                 "vehicle stopped unseen, e.g. while the server was down); 0: never")
      ->check(CLI::Range(0.0, 86400.0))
      ->capture_default_str();
  app.add_option("--queue", f.options.queue_capacity,
                 "Frames per session waiting for fusion before new ones are dropped")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  auto* cluster = app.add_option(
      "--cluster", f.cluster_url,
      "Run as one server of a cluster whose state is in this PostgreSQL database (a libpq URL, "
      "e.g. postgresql://stereomap@db.example:5432/stereomap; the password from PGPASSWORD or "
      "~/.pgpass, not the URL). Sessions are journaled there and spread over the cluster's "
      "servers; --store is not used");
  app.add_option("--server-id", f.server_id,
                 "This server's name in the cluster (letters, digits, . _ -; default: the host "
                 "name, process id and a random number)")
      ->needs(cluster);
  app.add_option("--advertise", f.advertise,
                 "Where the cluster's proxy reaches this server's HTTP, HOST:PORT (default: "
                 "--http's)")
      ->needs(cluster);
  app.add_option("--lease", f.lease_s,
                 "Seconds a server keeps its sessions without renewing its lease: a server "
                 "silent that long loses them to the others")
      ->check(CLI::Range(1.0, 600.0))
      ->needs(cluster)
      ->capture_default_str();
}

// Where and for whom the server listens: the address, the token and the viewer's files;
// nullopt (said) on bad usage.
std::optional<net::HttpServerOptions> httpOptions(const Flags& f) {
  net::HttpServerOptions http;
  const size_t colon = f.http_spec.rfind(':');
  try {
    if (colon == std::string::npos) throw std::invalid_argument("no port");
    http.address = f.http_spec.substr(0, colon);
    const int port = std::stoi(f.http_spec.substr(colon + 1));
    if (port < 0 || port > 65535) throw std::out_of_range("port");
    http.port = static_cast<uint16_t>(port);
  } catch (const std::exception&) {
    spdlog::error("--http '{}' must be ADDRESS:PORT, e.g. 127.0.0.1:8080", f.http_spec);
    return std::nullopt;
  }
  if (http.address == "localhost") http.address = "127.0.0.1";
  const auto token = resolveToken(f.token, f.token_file);
  if (!token) return std::nullopt;
  if (!f.tokens_file.empty()) {
    auto access = core::AccessList::load(f.tokens_file);
    if (!access) {
      spdlog::error("--tokens: {}", access.error().message);
      return std::nullopt;
    }
    http.access = std::move(access).value();
  }
  if (!token->empty()) http.access.add(core::Role::kOperator, *token, "token");
  if (f.tls_cert.empty() != f.tls_key.empty()) {
    spdlog::error("--tls-cert and --tls-key go together");
    return std::nullopt;
  }
  http.tls_cert = f.tls_cert;
  http.tls_key = f.tls_key;
  if (!isLoopback(http.address) && f.tls_cert.empty()) {
    if (!f.insecure_http) {
      spdlog::error(
          "--http {} is not a loopback address: serve https (--tls-cert FILE --tls-key FILE), or "
          "pass --insecure-http behind a proxy that terminates TLS",
          f.http_spec);
      return std::nullopt;
    }
    spdlog::warn(
        "--insecure-http: plain HTTP on {}; tokens and maps cross the network in clear unless a "
        "proxy in front terminates TLS",
        f.http_spec);
  }
  if (!isLoopback(http.address) && http.access.empty()) {
    spdlog::error(
        "--http {} is not a loopback address: give tokens (--tokens FILE, --token-file FILE or "
        "STEREOMAP_TOKEN) so that only your people can see and change the maps",
        f.http_spec);
    return std::nullopt;
  }
  http.web_root = f.web_root.empty()
                      ? std::filesystem::canonical("/proc/self/exe").parent_path() / ".." / "web"
                      : std::filesystem::path(f.web_root);
  http.web_root = std::filesystem::weakly_canonical(http.web_root);
  if (!std::filesystem::exists(http.web_root / "index.html")) {
    spdlog::warn(
        "no viewer at {} (build it with ./scripts/build, or pass --web-root); the API "
        "still works",
        http.web_root.string());
  }
  return http;
}

}  // namespace

int main(int argc, char** argv) {
  common::Shutdown shutdown;  // first: blocks SIGINT/SIGTERM for every later thread

  CLI::App app{"stereomap-server: fuse vehicles' clouds into live 3D maps and serve them"};
  Flags flags;
  addFlags(app, flags);
  if (auto exit_code = common::parseCommandLine(app, argc, argv)) return *exit_code;
  fusion::OctomapLogRoute octomap_log;  // after parsing: CLI11's errors stay on stderr
  const auto http = httpOptions(flags);
  if (!http) return 2;

  auto fail = [](const common::Error& error) {
    spdlog::error("{}", error.message);
    return 1;
  };
  proto::logSecurityDates(flags.dds);
  auto participant = proto::Participant::create(flags.dds);
  if (!participant) return fail(participant.error());

  if (!flags.cluster_url.empty())
    return app::runClusterServer(flags, *http, *participant, shutdown);
  return app::runSingleServer(flags, *http, *participant, shutdown);
}
