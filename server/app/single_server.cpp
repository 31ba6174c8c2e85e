// The single server: sessions journaled in files on its own disk, with a SQLite catalog
// (server/store), recovered at start; every DDS partition read.
#include <spdlog/spdlog.h>

#include <thread>

#include "server/app/run.hpp"
#include "server/core/frame_aligner.hpp"
#include "server/ingest/ack_router.hpp"
#include "server/ingest/dds_ingest.hpp"
#include "server/interop/session_mcap.hpp"
#include "server/store/session_journals.hpp"

namespace stereomap::app {

namespace {

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

}  // namespace

McapExport sessionMcap(const core::MapServer& server,
                       std::function<interop::JournalSource(const std::string& id)> journal_of) {
  return [&server, journal_of = std::move(journal_of)](
             const std::string& id, const std::function<bool(std::string_view)>& sink) {
    const auto session = server.find(id);
    if (!session) {
      return common::Status(common::makeError(
          common::ErrorCode::kNotFound, "no session '" + id +
                                            "' is loaded (a closed one: POST /api/sessions/" + id +
                                            "/open first)"));
    }
    auto written = interop::writeSessionMcap(*session, journal_of(id), sink);
    if (!written) return common::Status(written.error());
    return common::Status(common::Ok{});
  };
}

void serveUntilStopped(const Flags& f, core::MapServer& server, store::StoreAdmin* admin,
                       const net::HttpServer& http, const common::Shutdown& shutdown) {
  size_t last_voxels = 0;
  const auto vehicle_timeout =
      std::chrono::milliseconds(static_cast<int64_t>(f.vehicle_timeout_s * 1000));
  for (int tick = 1; !shutdown.waitFor(std::chrono::seconds(1)); ++tick) {
    if (vehicle_timeout.count() > 0) server.endSilentSessions(vehicle_timeout);
    if (tick % 5 != 0) continue;
    if (admin != nullptr) admin->checkpoint(/*all=*/false);
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

int runSingleServer(Flags& flags, const net::HttpServerOptions& http,
                    const std::shared_ptr<proto::Participant>& participant,
                    common::Shutdown& shutdown) {
  auto fail = [](const common::Error& error) {
    spdlog::error("{}", error.message);
    return 1;
  };
  // Journal first: a frame counts as received once it is on disk.
  store::SessionJournals journals(flags.store_dir, flags.options.resolution);
  flags.options.log = &journals;
  flags.options.snapshots = &journals;
  flags.options.archive = &journals;
  flags.options.snapshot_interval = std::chrono::milliseconds(
      static_cast<int64_t>(std::max(0.0, flags.snapshot_interval_s) * 1000));
  core::MapServer server(flags.options);
  auto admin = store::StoreAdmin::create(flags.store_dir, server, &journals,
                                         {.default_resolution = flags.options.resolution});
  if (!admin) return fail(admin.error());
  recoverSessions(**admin);
  // Vehicles in their own frame are aligned into their sessions' (until it is destroyed).
  core::FrameAligner aligner(server, {});
  // The readers only now: a vehicle sees the server once it takes samples. Created before the
  // recovery, they matched vehicles whose live poses then waited out the recovery in their
  // queues (a pose 200 ms old on arrival after a 5-minute outage; docs/BENCHMARKS.md); the
  // vehicles keep what is not acknowledged meanwhile.
  auto ingest =
      ingest::DdsIngest::create(participant, {proto::kEverySessionPartition}, /*events=*/true);
  if (!ingest) return fail(ingest.error());
  ingest::AckRouter acks(participant);

  net::HttpServerOptions http_options = http;
  http_options.session_mcap = sessionMcap(server, [root = flags.store_dir](const std::string& id) {
    return interop::journalFile(std::filesystem::path(root) / id / store::kJournalName);
  });
  auto http_server = net::HttpServer::create(http_options, server, admin->get());
  if (!http_server) return fail(http_server.error());
  (*http_server)->start();
  shutdown.onStop([&ingest] { (*ingest)->stop(); });
  (*ingest)->start(server);
  std::thread ack_sender([&] {
    ingest::sendAcksUntil(
        server, [&acks](const proto::AckMsg& ack) { return acks.send(ack); },
        [&shutdown](std::chrono::milliseconds period) { return shutdown.waitFor(period); });
  });
  spdlog::info("stereomap-server on DDS domain {}, resolution {} m, store {}", flags.dds.domain_id,
               flags.options.resolution, flags.store_dir);
  spdlog::info("viewer: {}://{}:{}/ (Foxglove: {}://{}:{}/foxglove)", (*http_server)->scheme(),
               http.address, (*http_server)->port(), (*http_server)->wsScheme(), http.address,
               (*http_server)->port());

  serveUntilStopped(flags, server, admin->get(), **http_server, shutdown);

  spdlog::info("stopping (signal {}): finishing queued frames and saving sessions",
               shutdown.signal());
  (*ingest)->join();
  ack_sender.join();
  (*http_server)->stop();
  for (const auto& session : server.sessions()) session->waitUntilFused();
  (*admin)->checkpoint(/*all=*/true);
  spdlog::info("stopped");
  return 0;
}

}  // namespace stereomap::app
