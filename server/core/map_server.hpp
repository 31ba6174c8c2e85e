// The server's core: validates every incoming sample, counts and logs the bad ones
// (rate-limited), and routes the good ones to their session (created on first sight).
// Thread-safe: ingest() may be called from several DDS reader threads at once.
#pragma once

#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "proto/messages.hpp"
#include "server/core/metrics.hpp"
#include "server/core/session.hpp"
#include "server/core/validate.hpp"

namespace stereomap::core {

struct MapServerOptions {
  double resolution = 0.1;
  size_t queue_capacity = 200;
  size_t max_sessions = 256;
  IngestLimits limits;
};

class MapServer {
 public:
  explicit MapServer(const MapServerOptions& options);

  // Each returns true when the sample was accepted.
  bool ingest(const proto::CloudFrameMsg& frame);
  bool ingest(const proto::PoseMsg& pose);
  bool ingest(const proto::SessionEventMsg& event);

  std::vector<std::shared_ptr<Session>> sessions() const;  // in creation order
  std::shared_ptr<Session> find(const std::string& id) const;
  // Prometheus text, with per-session gauges refreshed.
  std::string metricsText() const;
  const Metrics& metrics() const { return metrics_; }
  const MapServerOptions& options() const { return options_; }

 private:
  std::shared_ptr<Session> sessionFor(const std::string& id, const char* topic);
  // Counts the sample and returns its session, or nullptr (counted, logged) when rejected.
  std::shared_ptr<Session> admit(const char* topic, const std::string& vehicle_id,
                                 const std::string& session_id,
                                 const std::optional<Rejection>& rejection);
  void reject(const char* topic, const Rejection& rejection, const std::string& from);

  const MapServerOptions options_;
  mutable Metrics metrics_;
  mutable std::mutex mutex_;
  std::map<std::string, std::shared_ptr<Session>> sessions_;
  std::vector<std::string> order_;
  std::map<std::string, uint64_t> rejections_by_reason_;  // for rate-limited logging
};

}  // namespace stereomap::core
