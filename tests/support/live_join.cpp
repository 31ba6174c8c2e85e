#include "tests/support/live_join.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <map>
#include <thread>

#include "common/trajectory.hpp"
#include "tests/support/process.hpp"
#include "tests/support/server_fixture.hpp"

namespace stereomap::testing {

namespace {

using Clock = std::chrono::steady_clock;

nlohmann::json sessionJson(const ServerProcess& server, const std::string& id) {
  const auto reply = server.get("/api/sessions/" + id);
  if (reply.status != 200) return nullptr;
  return nlohmann::json::parse(reply.body, nullptr, false);
}

}  // namespace

// RMS of |T p_own - p_truth| over the poses both files have (by stamp).
double trajectoryError(const common::Rigid3& T, const std::string& own, const std::string& truth) {
  auto a = common::readTrajectory(own);
  auto b = common::readTrajectory(truth);
  if (!a || !b) return LiveJoinResult::kNaN;
  std::map<long long, common::Vec3> truth_at;
  for (const auto& p : *b) truth_at[std::llround(p.t * 1e6)] = p.pose.translation;
  double sum = 0;
  size_t n = 0;
  for (const auto& p : *a) {
    const auto found = truth_at.find(std::llround(p.t * 1e6));
    if (found == truth_at.end()) continue;
    sum += (T * p.pose.translation - found->second).squaredNorm();
    ++n;
  }
  return n > 0 ? std::sqrt(sum / static_cast<double>(n)) : LiveJoinResult::kNaN;
}

nlohmann::json vehicleFrame(const nlohmann::json& session, const std::string& vehicle) {
  if (!session.is_object() || !session.contains("vehicle_frames")) return nullptr;
  for (const auto& entry : session["vehicle_frames"]) {
    if (entry.value("vehicle_id", "") == vehicle) return entry;
  }
  return nullptr;
}

LiveJoinResult runLiveJoin(const LiveJoinOptions& o) {
  LiveJoinResult result;
  ServerProcess server(o.domain, {}, o.store);
  const std::string dir = makeTempDir("stereomap-livejoin");
  auto vehicle = [&](const std::string& id, int frames, std::vector<std::string> extra,
                     const std::string& source = "sim") {
    extra.insert(extra.end(), {"--vehicle", id, "--vo", "gt", "--rate", "10"});
    auto argv = onboardArgs(o.domain, o.session, frames, extra);
    *std::next(std::find(argv.begin(), argv.end(), "--source")) = source;
    return std::make_unique<ChildProcess>(argv, dir + "/" + id + ".log");
  };
  {
    auto first = vehicle("sim-1", o.first_frames, {});
    first->waitExit(scaledTimeout(std::chrono::seconds(120)));
  }
  waitUntil(scaledTimeout(std::chrono::seconds(30)), [&] {
    const auto s = sessionJson(server, o.session);
    return s.is_object() && s.value("fusion_backlog", 1) == 0;
  });
  const auto before = sessionJson(server, o.session);
  result.voxels_before = before.value("occupied_voxels", size_t{0});
  result.bounds_before = before.value("bounds", nlohmann::json());
  const std::string own = dir + "/own.tum", truth = dir + "/truth.tum";
  const auto started = Clock::now();
  auto second = vehicle("sim-2", o.second_frames,
                        {"--frame", "own", "--start-pose", o.start_pose, "--start",
                         std::to_string(o.start_s), "--trajectory-out", own, "--truth-out", truth});
  std::unique_ptr<ChildProcess> third;
  if (o.stranger) {
    third = vehicle("sim-3", o.second_frames, {"--frame", "own", "--start-pose", "-5,3,0,45"},
                    "sim:hall");
  }
  // Joined, and its held frames fused again in the session's frame.
  waitUntil(
      scaledTimeout(std::chrono::seconds(120)),
      [&] {
        const auto s = sessionJson(server, o.session);
        const auto f = vehicleFrame(s, "sim-2");
        if (f.is_object() && f.value("frame", "") == "aligned" && !s.value("refusing", true)) {
          result.fused_s = std::chrono::duration<double>(Clock::now() - started).count();
          return true;
        }
        return !second->running() && !(f.is_object() && f.value("frame", "") == "aligning");
      },
      std::chrono::milliseconds(100));
  second->waitExit(scaledTimeout(std::chrono::seconds(120)));
  if (third) third->waitExit(scaledTimeout(std::chrono::seconds(120)));
  waitUntil(scaledTimeout(std::chrono::seconds(60)), [&] {
    const auto s = sessionJson(server, o.session);
    return s.is_object() && s.value("fusion_backlog", 1) == 0 && !s.value("refusing", true);
  });
  result.session = sessionJson(server, o.session);
  const auto frame = vehicleFrame(result.session, "sim-2");
  if (frame.is_object()) {
    result.attempts = frame.value("attempts", uint64_t{0});
    result.aligned = frame.value("frame", "") == "aligned";
  }
  if (result.aligned) {
    result.aligned_s = frame.value("aligned_s", LiveJoinResult::kNaN);
    const auto& t = frame["transform"];
    const common::Rigid3 T{
        common::Quat(t[6].get<double>(), t[3].get<double>(), t[4].get<double>(),
                     t[5].get<double>()),
        common::Vec3(t[0].get<double>(), t[1].get<double>(), t[2].get<double>())};
    result.error_m = trajectoryError(T, own, truth);
  }
  result.stranger = vehicleFrame(result.session, "sim-3");
  if (o.kill_server) server.process().kill9();
  result.log = server.log();
  std::error_code ec;
  std::filesystem::remove_all(dir, ec);
  return result;
}

}  // namespace stereomap::testing
