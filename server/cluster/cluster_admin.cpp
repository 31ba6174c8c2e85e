#include "server/cluster/cluster_admin.hpp"

#include <spdlog/spdlog.h>

#include "server/cluster/cluster_node.hpp"

namespace stereomap::cluster {

void ClusterAdmin::attach(ClusterDb& db, std::string self, ClusterStore& store) {
  std::lock_guard lock(mutex_);
  db_ = &db;
  self_ = std::move(self);
  store_ = &store;
}

void ClusterAdmin::serveWith(ClusterNode* node) {
  std::lock_guard lock(mutex_);
  node_ = node;
}

common::Result<ClusterAdmin::Parts> ClusterAdmin::parts() const {
  std::lock_guard lock(mutex_);
  if (db_ == nullptr || store_ == nullptr || node_ == nullptr) {
    return common::makeError(common::ErrorCode::kUnavailable,
                             "this server has not joined the cluster yet");
  }
  return Parts{db_, store_, node_};
}

common::Status ClusterAdmin::open(const std::string& id) {
  auto p = parts();
  if (!p) return p.error();
  auto opened = [&]() -> common::Result<Ownership> {
    std::lock_guard lock(store_mutex_);
    return p->store->open(id, p->db->serverId());
  }();
  if (!opened) return opened.error();
  auto served = p->node->serveNow(*opened);
  refresh();
  return served;
}

common::Status ClusterAdmin::close(const std::string& id) {
  auto p = parts();
  if (!p) return p.error();
  // Served here: its readers stop and its map is snapshotted before it is let go.
  auto retired = p->node->retire(id, ClusterDb::Leaving::kClosed);
  if (!retired) {
    std::lock_guard lock(store_mutex_);
    retired = p->store->close(id);
  }
  refresh();
  return retired;
}

common::Status ClusterAdmin::remove(const std::string& id) {
  auto p = parts();
  if (!p) return p.error();
  {
    std::lock_guard lock(store_mutex_);
    if (auto removed = p->store->remove(id); !removed) return removed;
  }
  p->node->drop(id, "deleted by an operator");
  refresh();
  return common::Ok{};
}

common::Status ClusterAdmin::merge(const core::MergeRequest& request) {
  auto p = parts();
  if (!p) return p.error();
  {
    std::lock_guard lock(store_mutex_);
    if (auto merged = p->store->merge(request); !merged) return merged;
  }
  return open(request.into);  // as a single server's merge leaves it: opened read-only
}

common::Result<std::shared_ptr<core::Session>> ClusterAdmin::replay(const std::string& id,
                                                                    int64_t until_ns) const {
  auto p = parts();
  if (!p) return p.error();
  std::lock_guard lock(store_mutex_);
  return p->store->replay(id, until_ns);
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
  auto left = db->outOfMemory();
  if (!read || !left) {
    spdlog::warn("cluster: cannot read the directory (listings and routes stay as they were): {}",
                 !read ? read.error().message : left.error().message);
  }
  std::lock_guard lock(mutex_);
  if (read) placements_ = std::move(*read);
  if (left) {
    out_of_memory_.clear();
    for (const auto& row : *left) out_of_memory_.push_back(row.status());
  }
}

std::vector<ClusterDb::Placement> ClusterAdmin::placements() const {
  std::lock_guard lock(mutex_);
  return placements_;
}

std::vector<core::SessionStatus> ClusterAdmin::closedSessions() const {
  std::lock_guard lock(mutex_);
  return out_of_memory_;
}

std::vector<core::SessionStatus> ClusterAdmin::remoteSessions() const {
  std::vector<core::SessionStatus> out;
  const auto self = selfAddress();
  for (const auto& placement : placements()) {
    if (placement.http == self) continue;
    core::SessionStatus status;
    status.id = placement.ownership.session;
    status.resolution = placement.ownership.resolution;
    status.read_only = placement.ownership.read_only;
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
