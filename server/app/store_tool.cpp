#include "server/app/store_tool.hpp"

#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <thread>

#include "common/files.hpp"
#include "common/transform_args.hpp"
#include "server/align/map_diff.hpp"
#include "server/core/validate.hpp"

namespace stereomap::app {

namespace fs = std::filesystem;

int fail(const std::string& message) {
  spdlog::error("{}", message);
  return 1;
}

std::string megabytes(uint64_t bytes) {
  char text[32];
  std::snprintf(text, sizeof(text), "%.1f", static_cast<double>(bytes) / 1e6);
  return text;
}

int exportSessionMcap(const core::Session& session, const interop::JournalSource& journal,
                      const Args& a) {
  const auto start = std::chrono::steady_clock::now();
  const fs::path out = a.mcap_out;
  const fs::path partial = out.string() + ".partial";
  std::ofstream file(partial, std::ios::binary | std::ios::trunc);
  if (!file) return fail("cannot write " + partial.string());
  interop::McapExportOptions options;
  const bool tty = ::isatty(STDERR_FILENO) != 0;
  auto last = std::chrono::steady_clock::now();
  options.progress = [&](uint64_t records) {
    const auto now = std::chrono::steady_clock::now();
    if (now - last < std::chrono::seconds(1)) return;
    last = now;
    std::fprintf(stderr, tty ? "\r%llu journal records written" : "%llu journal records written\n",
                 static_cast<unsigned long long>(records));
  };
  auto written = interop::writeSessionMcap(
      session, journal,
      [&](std::string_view bytes) {
        file.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
        return file.good();
      },
      options);
  if (tty) std::fprintf(stderr, "\n");
  if (written && !file.flush()) written = common::makeError(common::ErrorCode::kIo, "flush");
  file.close();
  std::error_code ignored;
  if (!written) {
    fs::remove(partial, ignored);
    return fail("cannot write " + out.string() + ": " + written.error().message);
  }
  fs::rename(partial, out, ignored);
  if (ignored) return fail("cannot rename " + partial.string() + ": " + ignored.message());
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::printf(
      "%s: %llu messages (%llu poses, %llu clouds, %zu map cubes at level %u), %llu bytes, "
      "%.1f s\n",
      out.c_str(), static_cast<unsigned long long>(written->messages),
      static_cast<unsigned long long>(written->poses),
      static_cast<unsigned long long>(written->clouds), written->map_cubes, written->map_level,
      static_cast<unsigned long long>(written->bytes), seconds);
  if (written->unreadable_clouds > 0) {
    spdlog::warn("{} clouds did not decode and were left out", written->unreadable_clouds);
  }
  return 0;
}

int exportSessionFile(const core::Session& session, Args& a) {
  // grid: the band as map_server's two files, PREFIX.pgm and PREFIX.yaml naming it.
  const bool grid = a.request.format == "grid";
  const std::string prefix = a.out.empty() ? a.id : a.out;
  std::vector<std::pair<std::string, std::string>> files;  // (format, path)
  if (grid) {
    files = {{"pgm", prefix + ".pgm"}, {"yaml", prefix + ".yaml"}};
    a.request.grid_image = fs::path(prefix + ".pgm").filename().string();
  } else {
    files = {{a.request.format, a.out.empty() ? a.id + "." + a.request.format : a.out}};
  }
  for (const auto& [format, out] : files) {
    core::ExportRequest request = a.request;
    request.format = format;
    const auto exported = core::exportSession(session, a.id, request);
    if (!exported) return fail(exported.error().message);
    const std::string& content = exported->content;
    std::ofstream file(out, std::ios::binary | std::ios::trunc);
    file.write(content.data(), static_cast<std::streamsize>(content.size()));
    if (!file.flush()) return fail("cannot write " + out);
    std::printf("%s: %s bytes written\n", out.c_str(), std::to_string(content.size()).c_str());
  }
  return 0;
}

common::Result<core::MergeRequest> mergeRequestOf(const Args& a) {
  auto request = core::MergeRequest::pair(a.first, a.second, a.into);
  if (!a.transform.empty()) {
    const auto T = common::rigidFromTxyzQxyzw(a.transform);
    if (!T) {
      return common::makeError(
          common::ErrorCode::kInvalidArgument,
          "--transform: 7 finite numbers tx,ty,tz,qx,qy,qz,qw with a unit quaternion");
    }
    request.sources[1].T_into_source = *T;
  }
  return request;
}

namespace {

// Every core (the answer is the same on any number of threads). Progress on stderr.
align::AlignOptions toolAlignOptions() {
  return {.threads = std::max(1u, std::thread::hardware_concurrency()),
          .progress = [](const std::string& step) {
            std::fprintf(stderr, "align: %s\n", step.c_str());
          }};
}

// The alignment of b onto a, its details and its line printed; nullopt (the exit code in
// `code`) when it failed or was refused.
std::optional<align::Alignment> alignAndReport(const core::SessionMapSource& maps,
                                               const std::string& a, const std::string& b,
                                               int& code) {
  auto found = core::alignSessions(maps, a, b, toolAlignOptions());
  if (!found) {
    code = fail(found.error().message);
    return std::nullopt;
  }
  if (found->found) {
    std::printf(
        "confidence %.2f, agreement %.0f%% (%.0f%% of %zu cells off the large planes), %zu and %zu "
        "occupied voxels, cells of %.2f m for the search, %zu feature matches, %d poses "
        "compared\n",
        found->confidence, 100 * found->agreement, 100 * found->structure_agreement,
        found->structure_cells, found->voxels_a, found->voxels_b, found->working_cell_m,
        found->matches, found->poses_tried);
  }
  std::printf("%s\n", align::alignLine(a, b, *found).c_str());
  std::fflush(stdout);
  code = found->found ? 0 : kRefused;
  if (!found->found) return std::nullopt;
  return *found;
}

}  // namespace

int alignCommand(const core::SessionMapSource& maps, const Args& a) {
  int code = 0;
  alignAndReport(maps, a.first, a.second, code);
  return code;
}

int diffCommand(const core::SessionMapSource& maps, const KeepDiffSession& keep, const Args& a) {
  auto request = mergeRequestOf(a);  // its --transform
  if (!request) return fail(request.error().message);
  if (!a.into.empty() && !core::isValidId(a.into)) {
    return fail("--into: session id '" + a.into.substr(0, 80) + "' is not 1-64 of [A-Za-z0-9._-]");
  }
  common::Rigid3 T_a_b = request->sources[1].T_into_source;
  if (a.transform.empty()) {
    int code = 0;
    const auto found = alignAndReport(maps, a.first, a.second, code);
    if (!found) return code;
    T_a_b = found->T_a_b;
  }
  auto map_a = maps(a.first);
  if (!map_a) return fail(map_a.error().message);
  auto map_b = maps(a.second);
  if (!map_b) return fail(map_b.error().message);
  if ((*map_a)->resolution() != (*map_b)->resolution()) {
    return fail("the sessions' maps have different resolutions");
  }
  const auto diff = align::diffMaps(**map_a, **map_b, T_a_b);
  const size_t changed = diff.appeared.size() + diff.disappeared.size();
  if (!a.out.empty() || a.into.empty()) {
    const std::string out = a.out.empty() ? a.first + "-" + a.second + ".diff.ply" : a.out;
    if (auto written = common::writeFileAtomically(out, align::diffPly(diff)); !written) {
      return fail("cannot write " + out + ": " + written.error().message);
    }
    std::printf("%s: %zu changed voxels (green appeared, red disappeared), in %s's frame\n",
                out.c_str(), changed, a.first.c_str());
  }
  if (!a.into.empty()) {
    const nlohmann::json about = {{"diff",
                                   {{"first", a.first},
                                    {"second", a.second},
                                    {"appeared", diff.appeared.size()},
                                    {"disappeared", diff.disappeared.size()},
                                    {"unchanged", diff.unchanged.size()},
                                    {"unseen_by_first", diff.unseen_by_a},
                                    {"unseen_by_second", diff.unseen_by_b}}}};
    const double resolution = (*map_a)->resolution();
    if (auto kept = keep(a.into, resolution, align::diffOctomap(diff, resolution), about.dump());
        !kept) {
      return fail("cannot keep the diff as session '" + a.into + "': " + kept.error().message);
    }
    std::printf(
        "session '%s': the diff in %s's frame, %zu changed and %zu unchanged voxels; the viewer "
        "colours it with ?session=%s&colour=change (green appeared, red disappeared, grey "
        "unchanged)\n",
        a.into.c_str(), a.first.c_str(), changed, diff.unchanged.size(), a.into.c_str());
  }
  std::printf("%s\n", align::diffLine(a.first, a.second, diff).c_str());
  return 0;
}

int siteCommand(const core::SessionMapSource& maps, const MergeSessions& merge, const Args& a) {
  if (!core::isValidId(a.into)) {
    return fail("site: session id '" + a.into.substr(0, 80) + "' is not 1-64 of [A-Za-z0-9._-]");
  }
  auto plan = core::planSite(maps, a.sessions, toolAlignOptions(), [&](const core::SiteMember& m) {
    std::printf("%s\n", core::siteMemberLine(a.into, m).c_str());
    std::fflush(stdout);
  });
  if (!plan) return fail(plan.error().message);
  const size_t registered = plan->registered(), left_out = plan->members.size() - registered;
  if (registered < 2) {
    std::printf("site %s: none (no session aligns onto %s: nothing made)\n", a.into.c_str(),
                a.sessions.front().c_str());
    return kRefused;
  }
  auto merged = merge(plan->mergeRequest(a.into));
  if (!merged) return fail(merged.error().message);
  std::printf(
      "site %s: %zu of %zu sessions registered in %s's frame, %zu left out; %llu frames, %zu "
      "poses, %zu occupied voxels\n",
      a.into.c_str(), registered, plan->members.size(), a.sessions.front().c_str(), left_out,
      static_cast<unsigned long long>(merged->frames_fused), merged->poses,
      merged->occupied_voxels);
  return 0;
}

std::optional<core::MergeRequest> mergeRequestAligned(const core::SessionMapSource& maps,
                                                      const Args& a, int& code) {
  auto request = mergeRequestOf(a);
  if (!request) {
    code = fail(request.error().message);
    return std::nullopt;
  }
  if (a.align == "auto") {
    const auto found = alignAndReport(maps, a.first, a.second, code);
    if (!found) return std::nullopt;
    request->sources[1].T_into_source = found->T_a_b;
  }
  return *request;
}

}  // namespace stereomap::app
