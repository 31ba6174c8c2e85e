// A server in a cluster (--cluster URL): sessions journaled in PostgreSQL and spread over the
// cluster's servers (server/cluster); this one serves those it owns.
#include <spdlog/spdlog.h>

#include "server/app/run.hpp"
#include "server/cluster/cluster_admin.hpp"
#include "server/cluster/cluster_db.hpp"
#include "server/cluster/cluster_journal.hpp"
#include "server/cluster/cluster_node.hpp"
#include "server/cluster/cluster_store.hpp"
#include "server/cluster/pg.hpp"
#include "server/core/frame_aligner.hpp"

namespace stereomap::app {

int runClusterServer(Flags& flags, const net::HttpServerOptions& http,
                     const std::shared_ptr<proto::Participant>& participant,
                     common::Shutdown& shutdown) {
  auto fail = [](const common::Error& error) {
    spdlog::error("{}", error.message);
    return 1;
  };
  if (cluster::redactPassword(flags.cluster_url) != flags.cluster_url) {
    spdlog::warn(
        "--cluster holds a password, visible to every local user in the process list; "
        "prefer PGPASSWORD or a ~/.pgpass file");
  }
  auto journal = cluster::ClusterJournal::open(flags.cluster_url);
  if (!journal) return fail(journal.error());
  flags.options.log = journal->get();
  flags.options.snapshots = journal->get();
  flags.options.archive = journal->get();
  flags.options.snapshot_interval = std::chrono::milliseconds(static_cast<int64_t>(
      (flags.snapshot_interval_s < 0 ? 30 : flags.snapshot_interval_s) * 1000));
  core::MapServer server(flags.options);
  core::FrameAligner aligner(server, {});  // vehicles in their own frame, into their sessions'

  // The HTTP port first: with --http ADDRESS:0 it is known only once bound, and the cluster
  // must know where this server is reached before it is given sessions.
  cluster::ClusterAdmin admin;
  net::HttpServerOptions http_options = http;
  http_options.session_mcap =
      sessionMcap(server, [journal = journal->get()](const std::string& id) {
        return [journal, id](const std::function<void(proto::journal::JournalRecord &&)>& visit) {
          auto read = journal->forEachRecord(id, [&](proto::journal::JournalRecord&& record,
                                                     uint64_t) { visit(std::move(record)); });
          if (!read) return common::Status(read.error());
          return common::Status(common::Ok{});
        };
      });
  auto http_server = net::HttpServer::create(http_options, server, &admin);
  if (!http_server) return fail(http_server.error());
  const std::string advertise = flags.advertise.empty()
                                    ? http.address + ":" + std::to_string((*http_server)->port())
                                    : flags.advertise;
  auto db = cluster::ClusterDb::open(
      {.url = flags.cluster_url,
       .server_id = flags.server_id,
       .http = advertise,
       .lease = std::chrono::milliseconds(static_cast<int64_t>(flags.lease_s * 1000)),
       .capacity = flags.options.max_sessions});
  if (!db) return fail(db.error());
  auto store = cluster::ClusterStore::open(flags.cluster_url, **journal);
  if (!store) return fail(store.error());
  admin.attach(**db, advertise, **store);
  (*http_server)->start();
  auto node =
      cluster::ClusterNode::start({.default_resolution = flags.options.resolution,
                                   .admin = &admin,
                                   .on_superseded = [&shutdown] { shutdown.requestStop(); }},
                                  **db, **journal, server, participant);
  if (!node) return fail(node.error());
  admin.serveWith(node->get());
  spdlog::info("stereomap-server '{}' in the cluster at {}, DDS domain {}, resolution {} m",
               (*db)->serverId(), cluster::redactPassword(flags.cluster_url), flags.dds.domain_id,
               flags.options.resolution);
  spdlog::info("viewer: {}://{}:{}/ (this server; the cluster's proxy routes to every one)",
               (*http_server)->scheme(), http.address, (*http_server)->port());

  serveUntilStopped(flags, server, nullptr, **http_server, shutdown);

  if ((*node)->superseded()) {
    // Restarted elsewhere under the same id: that process serves this id's sessions now.
    admin.serveWith(nullptr);
    (*node)->stop();
    (*http_server)->stop();
    spdlog::error("stopped: superseded by a newer process with server id '{}'", (*db)->serverId());
    return 1;
  }
  spdlog::info("stopping (signal {}): handing this server's sessions back to the cluster",
               shutdown.signal());
  admin.serveWith(nullptr);
  (*node)->stop();
  (*http_server)->stop();
  spdlog::info("stopped");
  return 0;
}

}  // namespace stereomap::app
