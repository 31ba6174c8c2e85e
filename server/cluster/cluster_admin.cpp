#include "server/cluster/cluster_admin.hpp"

namespace stereomap::cluster {

namespace {

common::Error notInCluster(const char* what) {
  return common::makeError(common::ErrorCode::kUnavailable,
                           std::string(what) +
                               " is not offered in a cluster yet: the session stays live on its "
                               "server (a single server's store offers it)");
}

}  // namespace

common::Status ClusterAdmin::open(const std::string&) { return notInCluster("opening a session"); }
common::Status ClusterAdmin::close(const std::string&) { return notInCluster("closing a session"); }
common::Status ClusterAdmin::remove(const std::string&) {
  return notInCluster("deleting a session");
}
common::Status ClusterAdmin::merge(const core::MergeRequest&) {
  return notInCluster("merging sessions");
}
common::Result<std::shared_ptr<core::Session>> ClusterAdmin::replay(const std::string&,
                                                                    int64_t) const {
  return notInCluster("replaying a session");
}

void ClusterAdmin::attach(ClusterDb& db, std::string self) {
  std::lock_guard lock(mutex_);
  db_ = &db;
  self_ = std::move(self);
}

std::optional<std::string> ClusterAdmin::selfAddress() const {
  std::lock_guard lock(mutex_);
  if (db_ == nullptr) return std::nullopt;
  return self_;
}

void ClusterAdmin::refresh() {
  ClusterDb* db = nullptr;
  {
    std::lock_guard lock(mutex_);
    db = db_;
  }
  if (db == nullptr) return;
  auto read = db->directory();
  if (!read) return;
  std::lock_guard lock(mutex_);
  placements_ = std::move(*read);
}

std::vector<ClusterDb::Placement> ClusterAdmin::placements() const {
  std::lock_guard lock(mutex_);
  return placements_;
}

std::vector<core::SessionStatus> ClusterAdmin::remoteSessions() const {
  std::vector<core::SessionStatus> out;
  const auto self = selfAddress();
  for (const auto& placement : placements()) {
    if (placement.http == self) continue;
    core::SessionStatus status;
    status.id = placement.ownership.session;
    status.resolution = placement.ownership.resolution;
    status.server = placement.http;
    out.push_back(std::move(status));
  }
  return out;
}

std::optional<std::string> ClusterAdmin::routeTo(const std::string& id) const {
  for (const auto& placement : placements()) {
    if (placement.ownership.session == id) return placement.http;
  }
  return std::nullopt;
}

}  // namespace stereomap::cluster
