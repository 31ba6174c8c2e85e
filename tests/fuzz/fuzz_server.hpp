// For the fuzz targets of the server's front doors (REST, WebSocket): a real MapServer
// holding one fused session ("s", vehicle "v": a wall and a pose), and a SessionAdmin that
// stands in for the store and checks what the front door hands it: every id must already be
// valid (isValidId) and a replay's time non-negative. It refuses everything else as not
// found, so the store's disk is never touched by the fuzzer.
#pragma once

#include <memory>

#include "server/core/map_server.hpp"
#include "server/core/session_admin.hpp"
#include "server/core/validate.hpp"
#include "testing/synthetic.hpp"

namespace stereomap::fuzz {

inline core::MapServer& fusedServer() {
  static core::MapServer* server = [] {
    auto* made = new core::MapServer(core::MapServerOptions{});
    made->ingest(testing::planeFrame("v", "s", 1, testing::planeCloud(2.0, 0.5, 0.05)));
    proto::PoseMsg pose;
    pose.vehicle_id.assign(1, 'v');  // (gcc 12 warns falsely on = "v": -Wrestrict)
    pose.session_id.assign(1, 's');
    pose.seq = 1;
    pose.stamp_ns = 1000;
    made->ingest(pose);
    made->find("s")->waitUntilFused();
    return made;
  }();
  return *server;
}

class IdCheckingAdmin : public core::SessionAdmin {
 public:
  std::vector<core::SessionStatus> closedSessions() const override { return {}; }
  common::Status open(const std::string& id) override { return check(id); }
  common::Status close(const std::string& id) override { return check(id); }
  common::Status remove(const std::string& id) override { return check(id); }
  common::Status merge(const core::MergeRequest& request) override {
    for (const auto& source : request.sources) {
      checkId(source.id);
      if (!source.T_into_source.rotation.coeffs().allFinite() ||
          !source.T_into_source.translation.allFinite()) {
        __builtin_trap();
      }
    }
    return check(request.into);
  }
  common::Result<std::shared_ptr<core::Session>> replay(const std::string& id,
                                                        int64_t until_ns) const override {
    if (until_ns < 0) __builtin_trap();
    return check(id).error();
  }

 private:
  static void checkId(const std::string& id) {
    if (!core::isValidId(id)) __builtin_trap();
  }
  static common::Status check(const std::string& id) {
    checkId(id);
    return common::makeError(common::ErrorCode::kNotFound, "no session " + id);
  }
};

}  // namespace stereomap::fuzz
