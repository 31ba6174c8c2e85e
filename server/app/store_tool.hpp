// stereomap-store's pieces shared by its two back ends: a single server's store folder
// (store_main.cpp) and a cluster's database (store_cluster.cpp).
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "common/result.hpp"
#include "server/core/exports.hpp"
#include "server/core/session.hpp"
#include "server/core/session_admin.hpp"
#include "server/core/session_align.hpp"
#include "server/interop/session_mcap.hpp"

namespace stereomap::app {

// The command line, every subcommand's options.
struct Args {
  std::string root = "stereomap-store";
  double resolution = 0.1;
  bool as_json = false;
  std::vector<std::string> repair_ids;
  std::vector<std::string> compact_ids;
  bool compact_all = false;
  std::string id;
  core::ExportRequest request{.format = ""};
  std::string out;
  std::string mcap_out;
  bool yes = false;
  std::string map_file;
  std::string first, second, into;
  std::vector<double> transform;
  std::string align;                  // merge --align: "auto" or empty
  std::vector<std::string> sessions;  // site: the flights, the first giving the frame
  std::string cluster_url;
};

// Logs the message as an error; exit code 1.
int fail(const std::string& message);
std::string megabytes(uint64_t bytes);

// `export --format`: the session as a file (or grid: map_server's two files).
int exportSessionFile(const core::Session& session, Args& a);
// `export --mcap`: the session as MCAP (server/interop/session_mcap.hpp), written as the
// journal is read, into a temporary file renamed at the end; progress on stderr.
int exportSessionMcap(const core::Session& session, const interop::JournalSource& journal,
                      const Args& a);
// merge's sessions and --transform.
common::Result<core::MergeRequest> mergeRequestOf(const Args& a);

// align, diff and merge --align auto, over a store folder or a cluster: `maps` reads a
// session's map. Exit codes: 0, 1 (an error) or kRefused.
inline constexpr int kRefused = 3;  // the maps overlap too little, or ambiguously
// Prints the alignment's details and its line (align::alignLine, last).
int alignCommand(const core::SessionMapSource& maps, const Args& a);
// Keeps a diff as a new session `id` (diff --into): its map in OctoMap's full format (.ot),
// `about` (JSON text) describing it where the store keeps such things.
using KeepDiffSession = std::function<common::Status(
    const std::string& id, double resolution, const std::string& ot, const std::string& about)>;
// Aligns (or takes --transform), then writes the changes as a PLY (--out, the default) and/or
// as a session (--into, through `keep`), and prints the diff line.
int diffCommand(const core::SessionMapSource& maps, const KeepDiffSession& keep, const Args& a);
// merge's request, its transform found by aligning with --align auto (printed); nullopt with
// the exit code in `code` when it failed or was refused.
std::optional<core::MergeRequest> mergeRequestAligned(const core::SessionMapSource& maps,
                                                      const Args& a, int& code);

// Merges as asked and answers the merged session's status (closed).
using MergeSessions =
    std::function<common::Result<core::SessionStatus>(const core::MergeRequest& request)>;
// site: registers a.sessions into the first's frame (core::planSite, a line per session as it
// is decided), then merges those registered into session a.into. Exit kRefused (nothing
// made) when fewer than two could be registered.
int siteCommand(const core::SessionMapSource& maps, const MergeSessions& merge, const Args& a);

// Subcommand `command` against the cluster's database at a.cluster_url.
int runInCluster(const std::string& command, Args& a);

}  // namespace stereomap::app
