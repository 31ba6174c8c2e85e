// stereomap-server's two modes, beside its flags: a single server (a store of files and
// SQLite on its own disk: single_server.cpp) and a server in a cluster (PostgreSQL, sessions
// spread over servers: cluster_server.cpp). main.cpp parses the flags and runs one.
#pragma once

#include <functional>
#include <memory>
#include <string>

#include "common/shutdown.hpp"
#include "proto/dds.hpp"
#include "server/core/map_server.hpp"
#include "server/interop/session_mcap.hpp"
#include "server/net/http_server.hpp"
#include "server/store/store_admin.hpp"

namespace stereomap::app {

struct Flags {
  std::string http_spec = "127.0.0.1:8080";
  std::string store_dir = "stereomap-store";
  core::MapServerOptions options;
  proto::DdsOptions dds;
  std::string web_root;
  std::string token, token_file;
  std::string tokens_file;  // the access list: tokens by role (core::AccessList)
  std::string tls_cert, tls_key;
  bool insecure_http = false;  // plain HTTP off loopback (behind a proxy that terminates TLS)
  double vehicle_timeout_s = 60;
  double snapshot_interval_s = -1;  // -1: the mode's default
  // Cluster mode (empty url: the single server).
  std::string cluster_url;
  std::string server_id;  // empty: made up from the host name and process id
  std::string advertise;  // where others reach this server's HTTP (empty: --http's address)
  double lease_s = 4;
};

// Each returns the process's exit code once the shutdown was requested and everything saved.
int runSingleServer(Flags& flags, const net::HttpServerOptions& http,
                    const std::shared_ptr<proto::Participant>& participant,
                    common::Shutdown& shutdown);
int runClusterServer(Flags& flags, const net::HttpServerOptions& http,
                     const std::shared_ptr<proto::Participant>& participant,
                     common::Shutdown& shutdown);

// GET /api/sessions/{id}/session.mcap (net::HttpServerOptions::session_mcap): a loaded session
// (live or opened; a closed one answers 404 with how to open it), its records read by the
// source `journal_of(id)` gives.
using McapExport = std::function<common::Status(const std::string& session,
                                                const std::function<bool(std::string_view)>& sink)>;
McapExport sessionMcap(const core::MapServer& server,
                       std::function<interop::JournalSource(const std::string& id)> journal_of);

// Until the shutdown: every second ends silent sessions; every five saves what is due (with
// a store) and logs the maps' growth.
void serveUntilStopped(const Flags& f, core::MapServer& server, store::StoreAdmin* admin,
                       const net::HttpServer& http, const common::Shutdown& shutdown);

}  // namespace stereomap::app
