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

#include "common/shutdown.hpp"
#include "proto/dds_cli.hpp"
#include "server/core/map_server.hpp"
#include "server/fusion/octomap_log.hpp"
#include "server/net/http_server.hpp"
#include "server/store/store_admin.hpp"

namespace {

using namespace stereomap;

// Reads one topic until shutdown, handing every sample to the map server.
template <typename T>
void pump(proto::Reader<T>& reader, core::MapServer& server, const common::Shutdown& shutdown) {
  std::vector<T> batch;
  bool last_round = false;
  while (!last_round) {
    last_round = shutdown.stopRequested();  // after a stop: one more round for what arrived
    batch.clear();
    reader.take(batch, last_round ? std::chrono::milliseconds(0) : std::chrono::milliseconds(500));
    for (const auto& sample : batch) server.ingest(sample);
  }
}

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

}  // namespace

int main(int argc, char** argv) {
  common::Shutdown shutdown;  // first: blocks SIGINT/SIGTERM for every later thread

  CLI::App app{"stereomap-server: fuse vehicles' clouds into live 3D maps and serve them"};
  std::string http_spec = "127.0.0.1:8080";
  std::string store_dir = "stereomap-store";
  core::MapServerOptions options;
  proto::DdsOptions dds;
  std::string web_root;
  std::string token, token_file;
  app.add_option("--http", http_spec, "Address and port for HTTP and WebSocket")
      ->capture_default_str();
  app.add_option("--store", store_dir, "Directory where sessions are kept")->capture_default_str();
  app.add_option("--resolution", options.resolution, "Finest voxel edge, metres")
      ->check(CLI::Range(0.01, 2.0))
      ->capture_default_str();
  proto::addDdsFlags(app, dds);
  app.add_option("--web-root", web_root, "The built viewer (default: ../web beside this binary)");
  app.add_option("--token-file", token_file,
                 "File whose first line is the token clients must present (Authorization: "
                 "Bearer T or ?token=T); required when --http is not a loopback address. Or set "
                 "STEREOMAP_TOKEN in the environment");
  app.add_option("--token", token,
                 "The token itself (visible to every local user in the process list: prefer "
                 "--token-file or STEREOMAP_TOKEN)");
  app.add_option("--max-cloud-bytes", options.limits.max_payload_bytes,
                 "Largest accepted cloud payload, bytes")
      ->check(CLI::Range(size_t{1024}, proto::kMaxPayloadBytes))
      ->capture_default_str();
  app.add_option("--snapshot-every", options.snapshot_every,
                 "Fused frames between map snapshots (recovery replays only the journal after "
                 "the last one)")
      ->check(CLI::Range(1, 1000000))
      ->capture_default_str();
  double vehicle_timeout_s = 60;
  app.add_option("--vehicle-timeout", vehicle_timeout_s,
                 "Seconds without samples after which a live session counts as ended (its "
                 "vehicle stopped unseen, e.g. while the server was down); 0: never")
      ->check(CLI::Range(0.0, 86400.0))
      ->capture_default_str();
  app.add_option("--queue", options.queue_capacity,
                 "Frames per session waiting for fusion before new ones are dropped")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& error) {
    return app.exit(error) == 0 ? 0 : 2;
  }
  fusion::OctomapLogRoute octomap_log;  // after parsing: CLI11's errors stay on stderr

  net::HttpServerOptions http;
  const size_t colon = http_spec.rfind(':');
  try {
    if (colon == std::string::npos) throw std::invalid_argument("no port");
    http.address = http_spec.substr(0, colon);
    const int port = std::stoi(http_spec.substr(colon + 1));
    if (port < 0 || port > 65535) throw std::out_of_range("port");
    http.port = static_cast<uint16_t>(port);
  } catch (const std::exception&) {
    spdlog::error("--http '{}' must be ADDRESS:PORT, e.g. 127.0.0.1:8080", http_spec);
    return 2;
  }
  if (http.address == "localhost") http.address = "127.0.0.1";
  const auto resolved_token = resolveToken(token, token_file);
  if (!resolved_token) return 2;
  if (!isLoopback(http.address) && resolved_token->empty()) {
    spdlog::error(
        "--http {} is not a loopback address: give a token (--token-file FILE or "
        "STEREOMAP_TOKEN) so that only your operators can see the maps",
        http_spec);
    return 2;
  }
  http.token = *resolved_token;
  http.web_root = web_root.empty()
                      ? std::filesystem::canonical("/proc/self/exe").parent_path() / ".." / "web"
                      : std::filesystem::path(web_root);
  http.web_root = std::filesystem::weakly_canonical(http.web_root);
  if (!std::filesystem::exists(http.web_root / "index.html")) {
    spdlog::warn(
        "no viewer at {} (build it with ./scripts/build, or pass --web-root); the API "
        "still works",
        http.web_root.string());
  }

  auto participant = proto::Participant::create(dds);
  if (!participant) {
    spdlog::error("{}", participant.error().message);
    return 1;
  }
  auto clouds = proto::Reader<proto::CloudFrameMsg>::create(*participant);
  auto poses = proto::Reader<proto::PoseMsg>::create(*participant);
  auto events = proto::Reader<proto::SessionEventMsg>::create(*participant);
  auto corrections = proto::Reader<proto::PoseCorrectionMsg>::create(*participant);
  auto landing = proto::Reader<proto::LandingTargetMsg>::create(*participant);
  if (!clouds || !poses || !events || !corrections || !landing) {
    spdlog::error("cannot create DDS readers: {}", !clouds        ? clouds.error().message
                                                   : !poses       ? poses.error().message
                                                   : !events      ? events.error().message
                                                   : !corrections ? corrections.error().message
                                                                  : landing.error().message);
    return 1;
  }

  // Journal first: a frame counts as received once it is on disk. Then recover what earlier
  // runs journaled, before DDS delivers anything new.
  store::SessionJournals journals(store_dir, options.resolution);
  options.log = &journals;
  options.snapshots = &journals;
  options.archive = &journals;
  core::MapServer server(options);
  auto admin = store::StoreAdmin::create(store_dir, server, &journals,
                                         {.default_resolution = options.resolution});
  if (!admin) {
    spdlog::error("{}", admin.error().message);
    return 1;
  }
  if (!(*admin)->catalogWarning().empty()) spdlog::warn("{}", (*admin)->catalogWarning());
  for (const auto& session : (*admin)->recoverAll()) {
    if (!session.problem.empty()) {
      spdlog::warn(
          "session '{}': {} ({} records lost; `stereomap-store check` and `repair` "
          "say more)",
          session.id, session.problem, session.lost_records);
    }
    spdlog::info("session '{}' recovered: {} frames ({} from a snapshot), {} poses", session.id,
                 session.frames, session.snapshot_frames, session.poses);
  }

  auto http_server = net::HttpServer::create(http, server, admin->get());
  if (!http_server) {
    spdlog::error("{}", http_server.error().message);
    return 1;
  }
  (*http_server)->start();

  shutdown.onStop([&] {
    (*clouds)->wake();
    (*poses)->wake();
    (*events)->wake();
    (*corrections)->wake();
    (*landing)->wake();
  });
  std::vector<std::thread> ingest;
  ingest.emplace_back([&] { pump(**clouds, server, shutdown); });
  ingest.emplace_back([&] { pump(**poses, server, shutdown); });
  ingest.emplace_back([&] { pump(**events, server, shutdown); });
  ingest.emplace_back([&] { pump(**corrections, server, shutdown); });
  ingest.emplace_back([&] { pump(**landing, server, shutdown); });

  spdlog::info("stereomap-server on DDS domain {}, resolution {} m, store {}", dds.domain_id,
               options.resolution, store_dir);
  spdlog::info("viewer: http://{}:{}/", http.address, (*http_server)->port());

  size_t last_voxels = 0;
  const auto vehicle_timeout =
      std::chrono::milliseconds(static_cast<int64_t>(vehicle_timeout_s * 1000));
  for (int tick = 1; !shutdown.waitFor(std::chrono::seconds(1)); ++tick) {
    if (vehicle_timeout.count() > 0) server.endSilentSessions(vehicle_timeout);
    if (tick % 5 != 0) continue;
    (*admin)->checkpoint(/*all=*/false);
    size_t voxels = 0, frames = 0, backlog = 0;
    const auto sessions = server.sessions();
    for (const auto& session : sessions) {
      const auto status = session->status();
      voxels += status.occupied_voxels;
      frames += status.frames_fused;
      backlog += status.backlog;
    }
    if (voxels != last_voxels) {
      spdlog::info(
          "map: {} sessions, {} frames fused, {} occupied voxels (+{}), backlog {}, "
          "{} viewers",
          sessions.size(), frames, voxels,
          static_cast<long>(voxels) - static_cast<long>(last_voxels), backlog,
          (*http_server)->viewers());
      last_voxels = voxels;
    }
  }

  spdlog::info("stopping (signal {}): finishing queued frames and saving sessions",
               shutdown.signal());
  for (auto& thread : ingest) thread.join();
  (*http_server)->stop();
  for (const auto& session : server.sessions()) session->waitUntilFused();
  (*admin)->checkpoint(/*all=*/true);
  spdlog::info("stopped");
  return 0;
}
