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
#include "server/core/map_server.hpp"
#include "server/fusion/octomap_log.hpp"
#include "server/net/http_server.hpp"
#include "server/store/store_admin.hpp"

namespace {

using namespace stereomap;

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

struct Flags {
  std::string http_spec = "127.0.0.1:8080";
  std::string store_dir = "stereomap-store";
  core::MapServerOptions options;
  proto::DdsOptions dds;
  std::string web_root;
  std::string token, token_file;
  double vehicle_timeout_s = 60;
};

void addFlags(CLI::App& app, Flags& f) {
  app.add_option("--http", f.http_spec, "Address and port for HTTP and WebSocket")
      ->capture_default_str();
  app.add_option("--store", f.store_dir, "Directory where sessions are kept")
      ->capture_default_str();
  app.add_option("--resolution", f.options.resolution, "Finest voxel edge, metres")
      ->check(CLI::Range(0.01, 2.0))
      ->capture_default_str();
  proto::addDdsFlags(app, f.dds);
  app.add_option("--web-root", f.web_root, "The built viewer (default: ../web beside this binary)");
  app.add_option("--token-file", f.token_file,
                 "File whose first line is the token clients must present (Authorization: "
                 "Bearer T or ?token=T); required when --http is not a loopback address. Or set "
                 "STEREOMAP_TOKEN in the environment");
  app.add_option("--token", f.token,
                 "The token itself (visible to every local user in the process list: prefer "
                 "--token-file or STEREOMAP_TOKEN)");
  app.add_option("--max-cloud-bytes", f.options.limits.max_payload_bytes,
                 "Largest accepted cloud payload, bytes")
      ->check(CLI::Range(size_t{1024}, proto::kMaxPayloadBytes))
      ->capture_default_str();
  app.add_option("--snapshot-every", f.options.snapshot_every,
                 "Fused frames between map snapshots (recovery replays only the journal after "
                 "the last one)")
      ->check(CLI::Range(1, 1000000))
      ->capture_default_str();
  app.add_option("--vehicle-timeout", f.vehicle_timeout_s,
                 "Seconds without samples after which a live session counts as ended (its "
                 "vehicle stopped unseen, e.g. while the server was down); 0: never")
      ->check(CLI::Range(0.0, 86400.0))
      ->capture_default_str();
  app.add_option("--queue", f.options.queue_capacity,
                 "Frames per session waiting for fusion before new ones are dropped")
      ->check(CLI::Range(1, 100000))
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
  if (!isLoopback(http.address) && token->empty()) {
    spdlog::error(
        "--http {} is not a loopback address: give a token (--token-file FILE or "
        "STEREOMAP_TOKEN) so that only your operators can see the maps",
        f.http_spec);
    return std::nullopt;
  }
  http.token = *token;
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

// A reader per topic and a thread per reader handing its samples to the map server, from
// start() until the shutdown is requested (then one more round for what had arrived), and a
// thread telling the vehicles what is journaled (Ack, at most every kAckPeriod).
class DdsIngest {
 public:
  static constexpr std::chrono::milliseconds kAckPeriod{200};

  static common::Result<std::unique_ptr<DdsIngest>> create(
      const std::shared_ptr<proto::Participant>& participant) {
    auto ingest = std::unique_ptr<DdsIngest>(new DdsIngest);
    common::Status opened = common::Ok{};
    std::apply([&](auto&... readers) { (open(participant, readers, opened), ...); },
               ingest->readers_);
    if (!opened) return opened.error();
    auto acks = proto::Writer<proto::AckMsg>::create(participant);
    if (!acks)
      return common::makeError(acks.error().code,
                               "cannot create the DDS Ack writer: " + acks.error().message);
    ingest->acks_ = std::move(acks).value();
    return ingest;
  }

  void start(core::MapServer& server, common::Shutdown& shutdown) {
    shutdown.onStop(
        [this] { std::apply([](auto&... readers) { (readers->wake(), ...); }, readers_); });
    std::apply(
        [&](auto&... readers) {
          (threads_.emplace_back(
               [&server, &shutdown, reader = readers.get()] { pump(*reader, server, shutdown); }),
           ...);
        },
        readers_);
    threads_.emplace_back([this, &server, &shutdown] {
      do {
        for (const auto& ack : server.takeAcks()) {
          if (auto written = acks_->write(ack); !written) {
            spdlog::warn("cannot send an acknowledgement to '{}': {}", ack.vehicle_id,
                         written.error().message);
          }
        }
      } while (!shutdown.waitFor(kAckPeriod));
    });
  }

  void join() {
    for (auto& thread : threads_) thread.join();
    threads_.clear();
  }

 private:
  DdsIngest() = default;

  template <typename T>
  static void open(const std::shared_ptr<proto::Participant>& participant,
                   std::unique_ptr<proto::Reader<T>>& reader, common::Status& opened) {
    if (!opened) return;
    auto created = proto::Reader<T>::create(participant);
    if (!created) {
      opened = common::makeError(created.error().code,
                                 "cannot create DDS readers: " + created.error().message);
      return;
    }
    reader = std::move(created).value();
  }

  template <typename T>
  static void pump(proto::Reader<T>& reader, core::MapServer& server,
                   const common::Shutdown& shutdown) {
    std::vector<T> batch;
    std::vector<proto::RefusedSample> refused;
    bool last_round = false;
    while (!last_round) {
      last_round = shutdown.stopRequested();  // after a stop: one more round for what arrived
      batch.clear();
      refused.clear();
      reader.take(batch, last_round ? std::chrono::milliseconds(0) : std::chrono::milliseconds(500),
                  &refused);
      for (const auto& sample : refused) server.refuse(sample);
      for (const auto& sample : batch) server.ingest(sample);
    }
  }

  std::tuple<std::unique_ptr<proto::Reader<proto::CloudFrameMsg>>,
             std::unique_ptr<proto::Reader<proto::PoseMsg>>,
             std::unique_ptr<proto::Reader<proto::SessionEventMsg>>,
             std::unique_ptr<proto::Reader<proto::PoseCorrectionMsg>>,
             std::unique_ptr<proto::Reader<proto::LandingTargetMsg>>>
      readers_;
  std::unique_ptr<proto::Writer<proto::AckMsg>> acks_;
  std::vector<std::thread> threads_;
};

// What earlier runs journaled, fused again before DDS delivers anything new.
void recoverSessions(store::StoreAdmin& admin) {
  if (!admin.catalogWarning().empty()) spdlog::warn("{}", admin.catalogWarning());
  for (const auto& session : admin.recoverAll()) {
    if (!session.problem.empty()) {
      spdlog::warn(
          "session '{}': {} ({} records lost; `stereomap-store check` and `repair` "
          "say more)",
          session.id, session.problem, session.lost_records);
    }
    spdlog::info("session '{}' recovered: {} frames ({} from a snapshot), {} poses, in {:.1f} s",
                 session.id, session.frames, session.snapshot_frames, session.poses,
                 session.seconds);
  }
}

// Until the shutdown: every second ends silent sessions; every five saves what is due and
// logs the maps' growth.
void serveUntilStopped(const Flags& f, core::MapServer& server, store::StoreAdmin& admin,
                       const net::HttpServer& http, const common::Shutdown& shutdown) {
  size_t last_voxels = 0;
  const auto vehicle_timeout =
      std::chrono::milliseconds(static_cast<int64_t>(f.vehicle_timeout_s * 1000));
  for (int tick = 1; !shutdown.waitFor(std::chrono::seconds(1)); ++tick) {
    if (vehicle_timeout.count() > 0) server.endSilentSessions(vehicle_timeout);
    if (tick % 5 != 0) continue;
    admin.checkpoint(/*all=*/false);
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
          static_cast<long>(voxels) - static_cast<long>(last_voxels), backlog, http.viewers());
      last_voxels = voxels;
    }
  }
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
  auto participant = proto::Participant::create(flags.dds);
  if (!participant) return fail(participant.error());

  // Journal first: a frame counts as received once it is on disk.
  store::SessionJournals journals(flags.store_dir, flags.options.resolution);
  flags.options.log = &journals;
  flags.options.snapshots = &journals;
  flags.options.archive = &journals;
  core::MapServer server(flags.options);
  auto admin = store::StoreAdmin::create(flags.store_dir, server, &journals,
                                         {.default_resolution = flags.options.resolution});
  if (!admin) return fail(admin.error());
  recoverSessions(**admin);
  // The readers only now: a vehicle sees the server once it takes samples. Created before the
  // recovery, they matched vehicles whose live poses then waited out the recovery in their
  // queues (a pose 200 ms old on arrival after a 5-minute outage; docs/BENCHMARKS.md); the
  // vehicles keep what is not acknowledged meanwhile.
  auto ingest = DdsIngest::create(*participant);
  if (!ingest) return fail(ingest.error());

  auto http_server = net::HttpServer::create(*http, server, admin->get());
  if (!http_server) return fail(http_server.error());
  (*http_server)->start();
  (*ingest)->start(server, shutdown);
  spdlog::info("stereomap-server on DDS domain {}, resolution {} m, store {}", flags.dds.domain_id,
               flags.options.resolution, flags.store_dir);
  spdlog::info("viewer: http://{}:{}/", http->address, (*http_server)->port());

  serveUntilStopped(flags, server, **admin, **http_server, shutdown);

  spdlog::info("stopping (signal {}): finishing queued frames and saving sessions",
               shutdown.signal());
  (*ingest)->join();
  (*http_server)->stop();
  for (const auto& session : server.sessions()) session->waitUntilFused();
  (*admin)->checkpoint(/*all=*/true);
  spdlog::info("stopped");
  return 0;
}
