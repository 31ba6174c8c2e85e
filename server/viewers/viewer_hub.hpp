// Protocol 2 of the viewer WebSocket (/ws, docs/PROTOCOL.md) without the network: what each
// connected viewer asked for (hello, list, subscribe, view, trajectory), what it holds, and
// what it is sent next. The transport (server/net) only moves bytes: it asks next() for a
// message whenever its connection is idle and closes it when closing() says so.
//
// Fairness: each viewer has its own queue. Tiles are queued as keys, not bytes (a tile that
// changes again before it is sent is sent once, at its newest version; bytes are taken from
// the tile's shared encoding only when written), so a viewer that reads slowly costs the
// server a key per tile, not copies of the map. A viewer whose write has not finished for
// `stuck_after`, or whose unsent messages pass `max_queued_bytes`, is closed with a reason.
//
// Replays (the time slider: a stored session as it was at a moment) are made by the
// SessionAdmin on a thread of the hub's own and taken up by poll().
//
// Threads: one thread (the network thread) calls everything.
//
//   ViewerHub hub(map_server, admin, {});
//   auto id = hub.connect(/*authorised=*/false, now);
//   hub.receive(id, R"({"type": "hello", "protocol": 2, "token": "..."})", now);
//   while (auto message = hub.next(id, now)) { write(*message); hub.written(id); }
//   hub.poll(now);  // every few tens of milliseconds: pushes what changed
#pragma once

#include <chrono>
#include <cstdint>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "server/core/access.hpp"
#include "server/core/map_server.hpp"
#include "server/core/session_admin.hpp"
#include "server/viewers/endpoint.hpp"

namespace stereomap::viewers {

struct HubOptions {
  // A token of any role is required in the hello message when the list is not empty, unless
  // the connection's upgrade request carried one already.
  core::AccessList access;
  std::chrono::milliseconds stuck_after{10'000};  // a write unfinished this long: closed
  size_t max_queued_bytes = 4u << 20;             // unsent JSON per viewer: closed beyond
  std::chrono::milliseconds hello_within{10'000};
  size_t max_bad_messages = 16;      // malformed or unknown messages tolerated per connection
  uint64_t max_budget = 20'000'000;  // cells a view may ask for
  std::string server_name = "stereomap";
};

struct HubStats {
  size_t viewers = 0;
  uint64_t tiles_sent = 0, tile_bytes_sent = 0, messages_sent = 0;
  uint64_t closed_stuck = 0, closed_bad = 0;
};

class ViewerHub : public Endpoint {
 public:
  ViewerHub(const core::MapServer& server, const core::SessionAdmin* admin, HubOptions options);
  ~ViewerHub() override;
  ViewerHub(const ViewerHub&) = delete;
  ViewerHub& operator=(const ViewerHub&) = delete;

  // A new connection; `authorised`: its upgrade request carried the token (or none is set).
  Id connect(bool authorised, int64_t now_ns);
  void disconnect(Id id) override;
  // A text message from the viewer (JSON). Errors are answered; what must not go on closes.
  void receive(Id id, std::string_view text, int64_t now_ns) override;
  // A binary message from the viewer: not part of the protocol.
  void receiveBinary(Id id, std::string_view bytes) override;
  // Pushes to subscribers what changed since the last poll (tiles, poses, statuses) and
  // closes stuck or silent viewers.
  void poll(int64_t now_ns) override;
  // The next message for `id` while none is being written (nullopt: nothing to send now).
  std::optional<Outgoing> next(Id id, int64_t now_ns) override;
  void written(Id id) override;  // the message from next() has been written
  // Set when the viewer must be closed; the transport closes it and calls disconnect().
  std::optional<CloseOrder> closing(Id id) const override;
  std::vector<Id> ids() const;
  HubStats stats() const;

 private:
  struct Viewer;
  struct Feed;
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace stereomap::viewers
