// What a vehicle sends of its clouds over a thin radio link: what the server's map needs, not
// every pixel. Each cloud is thinned to one point per voxel of the map's grid (the centroid of
// the cloud's points in that voxel, so every ray still ends in the voxel it hit, and the
// map's hits are the same; no intensity, which the map does not use), quantised no finer
// than the voxel needs, and a cloud is sent only when it brings the map something: a
// share of voxels not sent recently, or the newest view after a while. A byte budget then
// holds the clouds under the link's rate (poses and events travel apart and never wait).
//
//   CloudLink link({.map_resolution_m = 0.1, .budget_bits_per_s = 1e6});
//   if (auto cloud = link.prepare(cloud_camera, T_map_camera, stamp_ns)) {
//     ... encode and publish *cloud ...
//     link.sent(stamp_ns, message_bytes, payload_bytes);
//   }
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include "common/geometry.hpp"
#include "common/point_cloud.hpp"
#include "common/result.hpp"
#include "proto/messages.hpp"

namespace stereomap::link {

struct CloudLinkOptions {
  // The server's map resolution: clouds are thinned to one point per voxel of it (0: sent
  // whole).
  double map_resolution_m = 0.1;
  // A cloud is sent when at least this share of its voxels was not sent in the last
  // refresh_s seconds (0: every cloud is sent)...
  double min_new_share = 0.1;
  double refresh_s = 2.0;
  // ... or when no cloud was sent for this long (the map keeps being confirmed and cleared).
  double max_interval_s = 1.0;
  // Cloud bytes per second on the link, payload and message (0: no budget). Where a whole
  // cloud every max_interval_s would overdraw it, clouds go out thinner (a share of their
  // voxels, a different share each time, so that a few clouds together cover the view);
  // a cloud that would still overdraw it is skipped.
  double budget_bits_per_s = 0;
  bool thinner_under_budget = true;  // false: rarer whole clouds only (for comparison)
};

struct CloudLinkStats {
  uint64_t offered = 0;         // clouds given to prepare()
  uint64_t sent = 0;            // clouds sent
  uint64_t skipped_empty = 0;   // skipped: no point (nothing in range), nothing for the map
  uint64_t skipped_known = 0;   // skipped: nothing new for the map
  uint64_t skipped_budget = 0;  // skipped: over the byte budget
  uint64_t thinned_budget = 0;  // sent with a share of their voxels, for the budget
  uint64_t points_in = 0, points_out = 0;
  uint64_t bytes = 0;  // as reported by sent()
};

// A link rate as operators write it: "1Mbit", "500kbit", "250k", "2M", "64000" (bits per
// second; k, M and G are powers of 1000, case aside; an optional "bit" or "bit/s", never
// "bps", which tc reads as bytes).
// "0" or "off": no budget (0). Anything else is an error naming the text.
common::Result<double> parseBitRate(const std::string& text);

// The clouds' share of a link of `link_bits_per_s` that also carries `pose_bits_per_s`:
// poses go first and are not counted against the clouds, and a tenth is left for DDS's own
// traffic (acknowledgements, heartbeats, resends on a lossy link). <= 0: no room for clouds.
double cloudShare(double link_bits_per_s, double pose_bits_per_s);

// The encoding that sends the link's clouds in the fewest bytes (stereomap-bench-link, sim
// rooms, docs/BENCHMARKS.md): Draco's kd-tree for thinned clouds (about a quarter smaller than
// quantised + zstd: one point per voxel is what an octree-like coder is for), quantised + zstd
// for whole clouds (as small as Draco there, and five times faster to encode).
proto::CloudEncoding bestEncoding(const CloudLinkOptions& options);

class CloudLink {
 public:
  explicit CloudLink(const CloudLinkOptions& options = {});

  // The cloud to send for this frame (thinned), or nullopt when this frame's cloud is better
  // not sent. T_map_camera: the camera's pose as sent with the cloud.
  std::optional<common::PointCloud> prepare(const common::PointCloud& cloud_camera,
                                            const common::Rigid3& T_map_camera, int64_t stamp_ns);
  // The quantisation bits for a cloud prepare() gave: the fewest (at most max_bits) that keep
  // each point within 1/64 of a voxel of where it was, so its voxel is the same or it was
  // within that of the face (max_bits when clouds are not thinned).
  int quantizationBits(const common::PointCloud& prepared, int max_bits) const;
  // The cloud prepare() gave was sent, `bytes` on the link of which `payload_bytes` were its
  // points (the rest: the message's fields and headers).
  void sent(int64_t stamp_ns, uint64_t bytes, uint64_t payload_bytes);

  const CloudLinkStats& stats() const { return stats_; }
  size_t memorySize() const { return sent_at_.size(); }  // voxels remembered as sent

 private:
  CloudLinkOptions options_;
  CloudLinkStats stats_;
  // Voxel key -> when a cloud holding it was last sent.
  std::unordered_map<uint64_t, int64_t> sent_at_;
  std::optional<int64_t> last_sent_ns_;
  // Token bucket of the budget, in bytes, and when it was last filled.
  double tokens_ = 0;
  std::optional<int64_t> filled_ns_;
  // A cloud's expected cost, from the last one sent: per point, and for its message.
  double bytes_per_point_ = 0;
  double message_bytes_ = 0;
  std::vector<uint64_t> pending_;  // the prepared cloud's voxel keys, until sent()
  size_t pending_points_ = 0;
  uint32_t share_phase_ = 0;    // where the next budget share of voxels starts (of 1024 slots)
  uint32_t pending_slots_ = 0;  // the prepared cloud's share, in slots (0: whole)
  size_t swept_size_ = 0;       // entries after the last sweep of old ones
};

}  // namespace stereomap::link
