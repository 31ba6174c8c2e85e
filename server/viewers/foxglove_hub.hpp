// The Foxglove WebSocket protocol (github.com/foxglove/ws-protocol, subprotocol
// foxglove.websocket.v1; clients offering foxglove.sdk.v1 get the same messages) without the
// network, so that Foxglove or Lichtblick open a live session as they open its MCAP export:
// the same channels (server/interop/foxglove_session.hpp), protobuf-encoded, with their
// descriptor sets.
//
// Per loaded session: /tf (foxglove.FrameTransform, every pose as it comes), per vehicle
// /vehicles/ID/trajectory (foxglove.PosesInFrame, the path so far, at most every
// trajectory_every) and /vehicles/ID/cloud (foxglove.CompressedPointCloud, Draco as the vehicle
// sent it; other encodings as foxglove.PointCloud on /vehicles/ID/cloud/points), /map
// (foxglove.SceneUpdate: cubes at the finest level whose cells fit max_map_cubes, an entity
// per 16-voxel block of each tile, encoded once for every client; when a tile changes, each
// client gets the blocks that changed since it was last sent it) and /map2d (foxglove.Grid of the
// ground band, made on a thread of the hub's own at most every grid_every while the map changes). A
// connection scoped to one session sees these topics as they are; an unscoped one sees every
// loaded session's, under /SESSION (e.g. /flight1/tf).
//
// A new subscriber gets the newest of each at once (each vehicle's newest transform, path and
// cloud, the whole map, the last grid). What a client has not read yet is coalesced: a newer
// path, cloud, grid or tile replaces the unsent older one (a tile is made into its message only
// when written); transforms are all kept. A client whose write has not finished for
// stuck_after, or whose unsent messages pass max_queued_bytes, is closed with the reason, as
// /ws closes a viewer; so is one that sends more than max_bad_messages bad ones (each is
// answered with a status message).
//
//   FoxgloveHub hub(map_server, {});
//   auto id = hub.connect("", now);  // serverInfo and advertise are queued
//   hub.receive(id, R"({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": 3}]})", now);
//   while (auto message = hub.next(id, now)) { write(*message); hub.written(id); }
//   hub.poll(now);  // every few tens of milliseconds
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <string_view>

#include "server/core/map_server.hpp"
#include "server/viewers/endpoint.hpp"

namespace stereomap::viewers {

struct FoxgloveOptions {
  std::chrono::milliseconds stuck_after{10'000};
  size_t max_queued_bytes = 4u << 20;
  size_t max_bad_messages = 16;
  size_t max_subscriptions = 1024;  // per connection
  size_t max_map_cubes = 250'000;
  std::chrono::milliseconds trajectory_every{1'000};
  std::chrono::milliseconds grid_every{2'000};
  double grid_above_m = 0.2, grid_below_m = 2.0;  // as the MCAP export's band
  std::string server_name = "stereomap";
};

struct FoxgloveStats {
  size_t clients = 0;
  uint64_t messages_sent = 0, bytes_sent = 0, closed_stuck = 0, closed_bad = 0;
};

class FoxgloveHub : public Endpoint {
 public:
  FoxgloveHub(const core::MapServer& server, FoxgloveOptions options);
  ~FoxgloveHub() override;
  FoxgloveHub(const FoxgloveHub&) = delete;
  FoxgloveHub& operator=(const FoxgloveHub&) = delete;

  // A new connection (authorised at its upgrade). `session`: only that session's channels,
  // named as in its MCAP export; "": every loaded session's, under /SESSION.
  Id connect(const std::string& session, int64_t now_ns);
  void disconnect(Id id) override;
  void receive(Id id, std::string_view text, int64_t now_ns) override;
  void receiveBinary(Id id, std::string_view bytes) override;
  void poll(int64_t now_ns) override;
  std::optional<Outgoing> next(Id id, int64_t now_ns) override;
  void written(Id id) override;
  std::optional<CloseOrder> closing(Id id) const override;
  FoxgloveStats stats() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace stereomap::viewers
