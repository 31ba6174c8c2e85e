#include "onboard/link/cloud_link.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <stdexcept>

#include "onboard/stereo/depth.hpp"
#include "proto/cloud_codec.hpp"

namespace stereomap::link {

namespace {

constexpr double kNsPerS = 1e9;
constexpr uint32_t kShareSlots = 1024;

// A voxel's slot in 0..kShareSlots-1, spread evenly over space (splitmix64's finaliser).
uint32_t slotOf(uint64_t key) {
  key = (key ^ (key >> 30)) * 0xbf58476d1ce4e5b9ULL;
  key = (key ^ (key >> 27)) * 0x94d049bb133111ebULL;
  return static_cast<uint32_t>((key ^ (key >> 31)) % kShareSlots);
}

}  // namespace

common::Result<double> parseBitRate(const std::string& text) {
  auto bad = [&] {
    // Quoted at most 40 characters long: the text comes from a command line or a file.
    const std::string shown = text.size() > 40 ? text.substr(0, 40) + "..." : text;
    return common::makeError(common::ErrorCode::kInvalidArgument,
                             "'" + shown + "' is not a bit rate (say 1Mbit, 500kbit or 64000)");
  };
  if (text == "off" || text == "0") return 0.0;
  size_t used = 0;
  double value = 0;
  try {
    value = std::stod(text, &used);
  } catch (const std::exception&) {
    return bad();
  }
  if (!std::isfinite(value) || value < 0) return bad();
  std::string unit = text.substr(used);
  for (char& c : unit) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  double scale = 1;
  if (!unit.empty() && (unit[0] == 'k' || unit[0] == 'm' || unit[0] == 'g')) {
    scale = unit[0] == 'k' ? 1e3 : unit[0] == 'm' ? 1e6 : 1e9;
    unit.erase(0, 1);
  }
  // Not "bps" or "b": tc reads "mbps" as megabytes per second.
  if (!unit.empty() && unit != "bit" && unit != "bit/s") return bad();
  if (!std::isfinite(value * scale)) return bad();  // 1e308M
  return value * scale;
}

double cloudShare(double link_bits_per_s, double pose_bits_per_s) {
  return 0.9 * link_bits_per_s - pose_bits_per_s;
}

proto::CloudEncoding bestEncoding(const CloudLinkOptions& options) {
  return options.map_resolution_m > 0 ? proto::CloudEncoding::kDraco
                                      : proto::CloudEncoding::kQuantZstd;
}

CloudLink::CloudLink(const CloudLinkOptions& options) : options_(options) {
  if (options.map_resolution_m < 0 || options.min_new_share < 0 || options.min_new_share > 1 ||
      options.refresh_s <= 0 || options.max_interval_s <= 0 || options.budget_bits_per_s < 0) {
    throw std::invalid_argument("CloudLinkOptions out of range");
  }
}

std::optional<common::PointCloud> CloudLink::prepare(const common::PointCloud& cloud_camera,
                                                     const common::Rigid3& T_map_camera,
                                                     int64_t stamp_ns) {
  ++stats_.offered;
  stats_.points_in += cloud_camera.size();
  common::PointCloud cloud = cloud_camera;
  if (options_.map_resolution_m > 0) {
    cloud = stereo::voxelGridDownsample(cloud_camera, options_.map_resolution_m, T_map_camera);
    cloud.intensity.clear();  // a fifth of a thinned cloud's bytes, and the map has no use for it
  }

  // A cloud without points has no ray to clear or hit anything with (a descent still above the
  // range): 58 kbit/s of nothing on the deck's descent before this.
  if (cloud.size() == 0) {
    ++stats_.skipped_empty;
    return std::nullopt;
  }

  // What the map has not had from this vehicle lately.
  pending_.clear();
  pending_slots_ = 0;
  size_t fresh = 0;
  const double voxel = options_.map_resolution_m > 0 ? options_.map_resolution_m : 0.1;
  const auto refresh_ns = static_cast<int64_t>(options_.refresh_s * kNsPerS);
  for (const auto& p : cloud.points) {
    const uint64_t key = stereo::gridKey(T_map_camera * p.cast<double>(), voxel);
    pending_.push_back(key);
    const auto it = sent_at_.find(key);
    fresh += it == sent_at_.end() || stamp_ns - it->second >= refresh_ns;
  }
  const bool due = !last_sent_ns_ || static_cast<double>(stamp_ns - *last_sent_ns_) >=
                                         options_.max_interval_s * kNsPerS;
  const bool news =
      static_cast<double>(fresh) >= options_.min_new_share * static_cast<double>(cloud.size());
  if (!due && !news) {
    ++stats_.skipped_known;
    return std::nullopt;
  }

  if (options_.budget_bits_per_s > 0) {
    // One second's worth of bytes at most is saved up (the link's queue stays short). The
    // bucket starts empty, not full: a full one let a 5 s drive send 6 s worth (KITTI's excerpt
    // at 979 kbit/s under a 1 Mbit budget); the first cloud, of unknown cost, goes anyway.
    const double rate = options_.budget_bits_per_s / 8;
    if (filled_ns_) {
      tokens_ += rate * static_cast<double>(std::max<int64_t>(stamp_ns - *filled_ns_, 0)) / kNsPerS;
    }
    tokens_ = std::min(tokens_, rate);
    filled_ns_ = stamp_ns;
    // Thinner clouds rather than rarer ones once a whole cloud per max_interval_s would not
    // fit: the map keeps being updated everywhere in view, at a lower density. Voxels are
    // taken by slot, and the next cloud starts where this one ended.
    const double whole = message_bytes_ + bytes_per_point_ * static_cast<double>(cloud.size());
    const double allowed = rate * options_.max_interval_s;
    if (whole > allowed && options_.map_resolution_m > 0 && options_.thinner_under_budget) {
      const double share = (allowed - message_bytes_) / (whole - message_bytes_);
      const auto slots = static_cast<uint32_t>(
          std::clamp(std::floor(kShareSlots * share), 1.0, 1.0 * kShareSlots));
      size_t kept = 0;
      for (size_t i = 0; i < cloud.size(); ++i) {
        if ((slotOf(pending_[i]) + kShareSlots - share_phase_) % kShareSlots >= slots) continue;
        cloud.points[kept] = cloud.points[i];
        pending_[kept++] = pending_[i];
      }
      cloud.points.resize(kept);
      pending_.resize(kept);
      pending_slots_ = slots;
      if (kept == 0) {  // this share of a small view is empty: the next cloud takes the next
        share_phase_ = (share_phase_ + slots) % kShareSlots;
        ++stats_.skipped_budget;
        return std::nullopt;
      }
    }
    // A cloud larger than a second's worth waits for a full bucket and leaves it in debt:
    // the rate still holds on average.
    const double expected = message_bytes_ + bytes_per_point_ * static_cast<double>(cloud.size());
    if (tokens_ < std::min(expected, rate)) {
      ++stats_.skipped_budget;
      return std::nullopt;
    }
  }
  pending_points_ = cloud.size();
  return cloud;
}

int CloudLink::quantizationBits(const common::PointCloud& prepared, int max_bits) const {
  if (options_.map_resolution_m <= 0) return max_bits;
  return proto::quantizationBitsFor(prepared, options_.map_resolution_m / 64, max_bits);
}

void CloudLink::sent(int64_t stamp_ns, uint64_t bytes, uint64_t payload_bytes) {
  ++stats_.sent;
  if (pending_slots_ > 0) {
    share_phase_ = (share_phase_ + pending_slots_) % kShareSlots;
    ++stats_.thinned_budget;
  }
  stats_.points_out += pending_points_;
  stats_.bytes += bytes;
  tokens_ -= static_cast<double>(bytes);
  if (pending_points_ > 0) {
    bytes_per_point_ = static_cast<double>(payload_bytes) / static_cast<double>(pending_points_);
  }
  message_bytes_ = static_cast<double>(bytes - std::min(bytes, payload_bytes));
  for (const uint64_t key : pending_) sent_at_[key] = stamp_ns;
  pending_.clear();
  last_sent_ns_ = stamp_ns;
  // Forget what is older than the refresh time once the memory has doubled since the last
  // sweep: memory stays proportional to what the vehicle sees in refresh_s.
  if (sent_at_.size() > 2 * swept_size_ + 1024) {
    const auto refresh_ns = static_cast<int64_t>(options_.refresh_s * kNsPerS);
    std::erase_if(sent_at_,
                  [&](const auto& entry) { return stamp_ns - entry.second >= refresh_ns; });
    swept_size_ = sent_at_.size();
  }
}

}  // namespace stereomap::link
