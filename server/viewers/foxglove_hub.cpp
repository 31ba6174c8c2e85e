#include "server/viewers/foxglove_hub.hpp"

#include <nlohmann/json.hpp>

#include <algorithm>
#include <deque>
#include <limits>
#include <map>
#include <set>
#include <unordered_map>
#include <vector>

#include "common/keyed_worker.hpp"
#include "common/time.hpp"
#include "server/foxglove/messages.hpp"
#include "server/interop/foxglove_session.hpp"
#include "server/viewers/json_nesting.hpp"

namespace stereomap::viewers {

namespace {

using foxglove::Schema;
using nlohmann::json;
using Text = std::shared_ptr<const std::string>;

constexpr int kMaxNesting = 4;  // subscribe nests 3 deep
constexpr size_t kMaxPathPoses = 1000;
constexpr uint8_t kMessageData = 0x01;  // the protocol's binary opcode

enum class Kind { kTf, kTrajectory, kCloud, kMap, kGrid };

struct Channel {
  std::string session, topic;  // topic as the session's MCAP names it
  Kind kind;
  Schema schema;
};

Text textOf(const json& message) {
  return std::make_shared<const std::string>(
      message.dump(-1, ' ', false, json::error_handler_t::replace));
}

// A message to one subscription. A map tile's is made when written (`payload` null).
struct Slot {
  uint32_t subscription = 0;
  uint64_t time = 0;
  Text payload;
  std::string session;
  tiles::TileKey tile;
  std::string key;  // coalescing: a newer slot of the same key replaces it ("": never)
};

struct Client {
  std::string scope;  // "": every session
  std::optional<CloseOrder> close;
  size_t bad = 0;
  std::deque<Text> control;  // JSON, sent before data
  std::deque<std::shared_ptr<Slot>> data;
  std::unordered_map<std::string, std::shared_ptr<Slot>> pending;  // by coalescing key
  size_t queued_bytes = 0;
  std::map<uint32_t, uint32_t> subscriptions;         // id -> channel
  std::map<uint32_t, std::set<uint32_t>> by_channel;  // channel -> subscription ids
  std::set<uint32_t> advertised;
  // What each /map subscription holds of each tile: its blocks' content hashes.
  std::map<std::pair<uint32_t, tiles::TileKey>, std::map<uint16_t, uint64_t>> held;
  bool writing = false;
  int64_t write_started_ns = 0;

  bool sees(const std::string& session) const { return scope.empty() || scope == session; }
};

// What has been taken from one session so far.
struct Feed {
  std::map<std::pair<Kind, std::string>, uint32_t> channels;  // by kind and vehicle (or "")
  size_t poses = 0;
  uint64_t trajectory_version = 0;
  std::map<std::string, std::vector<common::Rigid3>> paths;  // by vehicle
  std::map<std::string, int64_t> newest_stamp;               // by vehicle
  std::set<std::string> paths_changed;
  int64_t paths_sent_ns = 0;
  uint64_t tile_version = 0;
  unsigned map_level = 0;
  bool map_level_current = false;  // false: choose it again before tiles are sent
  double z_low = 0, z_span = 1;    // the cubes' colours by height: set with the level
  uint64_t level_epoch = 0;        // bumps when the level (or the colours) change
  int64_t map_changed_ns = 0;
  // Each tile's blocks as SceneUpdate fields, made once for every subscriber.
  struct Block {
    uint64_t hash = 0;  // of its cubes
    std::string field;
  };
  struct EncodedTile {
    uint64_t version = 0, epoch = 0;
    std::map<uint16_t, Block> blocks;
  };
  std::map<tiles::TileKey, EncodedTile> encoded;
  uint64_t cloud_number = 0;
  std::map<std::string, std::shared_ptr<const proto::CloudFrameMsg>> newest_cloud;  // by vehicle
  Text grid;                  // the newest grid made
  uint64_t grid_version = 0;  // the map version the newest grid asked for was made of
  int64_t grid_asked_ns = 0;
  bool grid_asked = false;
};

std::string cloudKey(const std::string& vehicle, Schema schema) {
  return vehicle + (schema == Schema::kPointCloud ? "/points" : "");
}

}  // namespace

struct FoxgloveHub::Impl {
  Impl(const core::MapServer& server, FoxgloveOptions options)
      : server(server), options(std::move(options)), hub_started_ns(common::nowNs()) {
    for (Schema schema : {Schema::kFrameTransform, Schema::kPosesInFrame, Schema::kPointCloud,
                          Schema::kCompressedPointCloud, Schema::kSceneUpdate, Schema::kGrid}) {
      schemas[schema] = foxglove::base64(foxglove::descriptorSet(schema));
    }
  }

  const core::MapServer& server;
  const FoxgloveOptions options;
  const int64_t hub_started_ns;
  std::map<Schema, std::string> schemas;  // base64 descriptor sets
  std::map<Id, Client> clients;
  Id next_id = 1;
  std::map<uint32_t, Channel> channels;
  uint32_t next_channel = 1;
  bool channels_added = false;
  std::map<std::string, Feed> feeds;
  common::KeyedWorker<std::string, common::Result<interop::GroundGrid>> grids;  // by session
  FoxgloveStats stats;

  // --- connections ------------------------------------------------------------------------

  void closeClient(Client& client, uint16_t code, std::string reason) {
    if (client.close) return;
    client.close = CloseOrder{code, std::move(reason)};
    client.control.clear();
    client.data.clear();
    client.pending.clear();
    client.queued_bytes = 0;
  }

  void status(Client& client, int level, const std::string& message) {
    client.control.push_back(textOf({{"op", "status"}, {"level", level}, {"message", message}}));
  }

  void bad(Client& client, const std::string& message) {
    ++client.bad;
    status(client, 2, message);
    if (client.bad > options.max_bad_messages) {
      ++stats.closed_bad;
      closeClient(client, 1008, "too many bad messages (" + std::to_string(client.bad) + ")");
    }
  }

  std::string topicFor(const Client& client, const Channel& channel) const {
    return client.scope.empty() ? "/" + channel.session + channel.topic : channel.topic;
  }

  // Tells each client the channels it sees and has not been told of.
  void advertiseNew() {
    if (!channels_added) return;
    channels_added = false;
    for (auto& [id, client] : clients) {
      if (client.close) continue;
      json list = json::array();
      for (const auto& [channel_id, channel] : channels) {
        if (!client.sees(channel.session) || !client.advertised.insert(channel_id).second) {
          continue;
        }
        list.push_back({{"id", channel_id},
                        {"topic", topicFor(client, channel)},
                        {"encoding", "protobuf"},
                        {"schemaName", foxglove::schemaName(channel.schema)},
                        {"schema", schemas[channel.schema]},
                        {"schemaEncoding", "protobuf"}});
      }
      if (!list.empty())
        client.control.push_back(textOf({{"op", "advertise"}, {"channels", list}}));
    }
  }

  void dropSubscription(Client& client, uint32_t subscription) {
    const auto found = client.subscriptions.find(subscription);
    if (found == client.subscriptions.end()) return;
    auto& subs = client.by_channel[found->second];
    subs.erase(subscription);
    if (subs.empty()) client.by_channel.erase(found->second);
    client.subscriptions.erase(found);
    std::erase_if(client.held,
                  [&](const auto& entry) { return entry.first.first == subscription; });
    std::erase_if(client.data, [&](const std::shared_ptr<Slot>& slot) {
      if (slot->subscription != subscription) return false;
      if (slot->payload) client.queued_bytes -= slot->payload->size();
      if (!slot->key.empty()) client.pending.erase(slot->key);
      return true;
    });
  }

  // Channels of sessions no longer loaded: unadvertised, with their subscriptions.
  void dropGoneSessions(const std::set<std::string>& loaded) {
    std::vector<uint32_t> gone;
    for (const auto& [id, channel] : channels) {
      if (!loaded.count(channel.session)) gone.push_back(id);
    }
    for (auto it = feeds.begin(); it != feeds.end();) {
      it = loaded.count(it->first) ? std::next(it) : feeds.erase(it);
    }
    if (gone.empty()) return;
    for (auto& [id, client] : clients) {
      json told = json::array();
      for (const uint32_t channel : gone) {
        if (!client.advertised.erase(channel)) continue;
        told.push_back(channel);
        const auto subs = client.by_channel[channel];
        for (const uint32_t sub : subs) dropSubscription(client, sub);
        client.by_channel.erase(channel);
      }
      if (!told.empty() && !client.close) {
        client.control.push_back(textOf({{"op", "unadvertise"}, {"channelIds", told}}));
      }
    }
    for (const uint32_t channel : gone) channels.erase(channel);
  }

  // --- queues -----------------------------------------------------------------------------

  void enqueue(Client& client, std::shared_ptr<Slot> slot) {
    if (client.close) return;
    const size_t bytes = slot->payload ? slot->payload->size() : 0;
    if (!slot->key.empty()) {
      if (auto found = client.pending.find(slot->key); found != client.pending.end()) {
        Slot& queued = *found->second;  // keeps its place in the queue, takes the newer bytes
        client.queued_bytes -= queued.payload ? queued.payload->size() : 0;
        queued.payload = std::move(slot->payload);
        queued.time = slot->time;
        client.queued_bytes += bytes;
        return;
      }
      client.pending[slot->key] = slot;
    }
    client.queued_bytes += bytes;
    client.data.push_back(std::move(slot));
    if (client.queued_bytes > options.max_queued_bytes) {
      ++stats.closed_stuck;
      closeClient(client, 1008,
                  "client too slow: more than " + std::to_string(options.max_queued_bytes >> 20) +
                      " MB of messages unread");
    }
  }

  bool subscribed(uint32_t channel) const {
    return std::any_of(clients.begin(), clients.end(),
                       [&](const auto& c) { return c.second.by_channel.count(channel) > 0; });
  }

  // `payload` to every subscription of `channel`; `coalesce`: a newer one replaces it unsent.
  void publish(uint32_t channel, int64_t time, const Text& payload, bool coalesce) {
    for (auto& [id, client] : clients) {
      const auto subs = client.by_channel.find(channel);
      if (subs == client.by_channel.end()) continue;
      for (const uint32_t sub : subs->second) send(client, sub, time, payload, coalesce);
    }
  }

  void send(Client& client, uint32_t sub, int64_t time, const Text& payload, bool coalesce) {
    auto slot = std::make_shared<Slot>();
    slot->subscription = sub;
    slot->time = static_cast<uint64_t>(std::max<int64_t>(time, 0));
    slot->payload = payload;
    if (coalesce) slot->key = std::to_string(sub);
    enqueue(client, std::move(slot));
  }

  void sendTile(Client& client, uint32_t sub, const std::string& session, const tiles::TileKey& key,
                int64_t time) {
    auto slot = std::make_shared<Slot>();
    slot->subscription = sub;
    slot->time = static_cast<uint64_t>(std::max<int64_t>(time, 0));
    slot->session = session;
    slot->tile = key;
    slot->key = std::to_string(sub) + "/" + key.text();
    enqueue(client, std::move(slot));
  }

  // --- sessions ---------------------------------------------------------------------------

  uint32_t channelFor(Feed& feed, const std::string& session, Kind kind, const std::string& vehicle,
                      Schema schema, std::string topic) {
    auto [it, added] = feed.channels.try_emplace({kind, vehicle}, 0);
    if (added) {
      it->second = next_channel++;
      channels[it->second] = {session, std::move(topic), kind, schema};
      channels_added = true;
    }
    return it->second;
  }

  Feed& feedFor(const std::string& session) {
    auto [it, added] = feeds.try_emplace(session);
    if (added) {
      channelFor(it->second, session, Kind::kTf, "", Schema::kFrameTransform, "/tf");
      channelFor(it->second, session, Kind::kMap, "", Schema::kSceneUpdate, "/map");
      channelFor(it->second, session, Kind::kGrid, "", Schema::kGrid, "/map2d");
    }
    return it->second;
  }

  // Everything new in every session some client sees.
  void sync(int64_t now_ns) {
    const auto sessions = server.sessions();
    std::set<std::string> loaded;
    for (const auto& session : sessions) loaded.insert(session->id());
    dropGoneSessions(loaded);
    for (const auto& session : sessions) {
      const bool seen = std::any_of(clients.begin(), clients.end(), [&](const auto& c) {
        return !c.second.close && c.second.sees(session->id());
      });
      if (!seen) {  // its paths and channels are made again if a client comes back
        if (feeds.erase(session->id())) {
          std::erase_if(channels, [&](const auto& c) { return c.second.session == session->id(); });
        }
        continue;
      }
      Feed& feed = feedFor(session->id());
      syncPoses(*session, feed);
      syncPaths(feed, now_ns);
      syncClouds(*session, feed);
      syncMap(*session, feed);
      askGrid(session, feed, now_ns);
    }
    takeGrids();
    advertiseNew();
  }

  // New poses: each vehicle's path, and a transform each to /tf's subscribers.
  void syncPoses(const core::Session& session, Feed& feed) {
    std::vector<core::PoseRecord> poses;
    const uint64_t version = session.trajectoryVersion();
    if (version != feed.trajectory_version) {  // a correction: every path again
      feed.trajectory_version = version;
      feed.paths.clear();
      const auto all = session.trajectory();
      for (const auto& pose : all) {
        if (!pose.held) feed.paths[pose.vehicle_id].push_back(pose.T_map_body);
      }
      for (const auto& [vehicle, path] : feed.paths) feed.paths_changed.insert(vehicle);
      poses.assign(all.begin() + static_cast<long>(std::min(feed.poses, all.size())), all.end());
      feed.poses = all.size();
    } else {
      poses = session.trajectory(feed.poses);
      feed.poses += poses.size();
      for (const auto& pose : poses) {
        if (pose.held) continue;
        feed.paths[pose.vehicle_id].push_back(pose.T_map_body);
        feed.paths_changed.insert(pose.vehicle_id);
      }
    }
    // A vehicle in its own frame, not aligned yet: nowhere in the map's frame (until its join
    // bumps the version and every path is sent again).
    std::erase_if(poses, [](const core::PoseRecord& pose) { return pose.held; });
    const uint32_t tf = feed.channels.at({Kind::kTf, ""});
    const bool wanted = subscribed(tf);
    for (const auto& pose : poses) {
      channelFor(feed, session.id(), Kind::kTrajectory, pose.vehicle_id, Schema::kPosesInFrame,
                 interop::trajectoryTopic(pose.vehicle_id));
      auto& newest = feed.newest_stamp[pose.vehicle_id];
      newest = std::max(newest, pose.stamp_ns);
      if (wanted) {
        publish(tf, pose.stamp_ns,
                std::make_shared<const std::string>(foxglove::frameTransform(
                    pose.stamp_ns, interop::kMapFrame, pose.vehicle_id, pose.T_map_body)),
                false);
      }
    }
  }

  Text pathMessage(const Feed& feed, const std::string& vehicle) const {
    const auto path = feed.paths.find(vehicle);
    const auto stamp = feed.newest_stamp.find(vehicle);
    const int64_t t = stamp == feed.newest_stamp.end() ? 0 : stamp->second;
    return std::make_shared<const std::string>(foxglove::posesInFrame(
        t, interop::kMapFrame,
        interop::thinned(path == feed.paths.end() ? std::vector<common::Rigid3>{} : path->second,
                         kMaxPathPoses)));
  }

  void syncPaths(Feed& feed, int64_t now_ns) {
    if (feed.paths_changed.empty() ||
        now_ns - feed.paths_sent_ns < std::chrono::nanoseconds(options.trajectory_every).count()) {
      return;
    }
    feed.paths_sent_ns = now_ns;
    for (const auto& vehicle : feed.paths_changed) {
      const auto channel = feed.channels.find({Kind::kTrajectory, vehicle});
      if (channel == feed.channels.end() || !subscribed(channel->second)) continue;
      publish(channel->second, feed.newest_stamp[vehicle], pathMessage(feed, vehicle), true);
    }
    feed.paths_changed.clear();
  }

  void syncClouds(const core::Session& session, Feed& feed) {
    for (auto& [number, frame] : session.liveClouds(feed.cloud_number)) {
      feed.cloud_number = std::max(feed.cloud_number, number);
      const Schema schema = frame->encoding == proto::CloudEncoding::kDraco
                                ? Schema::kCompressedPointCloud
                                : Schema::kPointCloud;
      const uint32_t channel =
          channelFor(feed, session.id(), Kind::kCloud, cloudKey(frame->vehicle_id, schema), schema,
                     interop::cloudTopic(frame->vehicle_id, schema));
      feed.newest_cloud[cloudKey(frame->vehicle_id, schema)] = frame;
      if (!subscribed(channel)) continue;
      const auto placed = interop::framePlacement(session, frame->vehicle_id);
      if (!placed) continue;  // held apart: nowhere in the map's frame yet
      if (auto cloud = interop::cloudMessage(*frame, *placed)) {
        publish(channel, frame->stamp_ns,
                std::make_shared<const std::string>(std::move(cloud->bytes)), true);
      }
    }
  }

  // The map's level for a session's subscribers, and its colours' height range (kept until
  // the level changes: a tile's cubes keep their colours as the map grows).
  void chooseLevel(Feed& feed, const std::vector<tiles::TileInfo>& list,
                   const common::Box3& bounds) {
    const unsigned level = interop::mapLevel(list, options.max_map_cubes);
    if (feed.map_level_current && level == feed.map_level) return;
    feed.map_level = level;
    feed.map_level_current = true;
    feed.z_low = bounds.empty() ? 0 : bounds.min.z();
    feed.z_span = bounds.empty() ? 1 : bounds.max.z() - bounds.min.z();
    ++feed.level_epoch;
    feed.encoded.clear();
  }

  void syncMap(const core::Session& session, Feed& feed) {
    const auto& tiles = session.tiles();
    const auto summary = tiles.summary();
    if (summary.version == feed.tile_version) return;
    const uint32_t channel = feed.channels.at({Kind::kMap, ""});
    if (!subscribed(channel)) {  // a first subscriber chooses the level (sendNewest)
      feed.tile_version = summary.version;
      feed.map_changed_ns = summary.changed_ns;
      feed.map_level_current = false;
      feed.encoded.clear();
      return;
    }
    auto changed = tiles.changedSince(feed.tile_version);
    const auto list = tiles.list();
    const uint64_t epoch = feed.level_epoch;
    chooseLevel(feed, list, summary.bounds);
    feed.tile_version = summary.version;
    feed.map_changed_ns = summary.changed_ns;
    if (!changed || epoch != feed.level_epoch) {  // every tile again
      changed.emplace();
      for (const auto& info : list) changed->emplace_back(info.key, info.version);
    }
    for (auto& [id, client] : clients) {
      const auto subs = client.by_channel.find(channel);
      if (subs == client.by_channel.end()) continue;
      for (const uint32_t sub : subs->second) {
        for (const auto& [key, version] : *changed) {
          sendTile(client, sub, session.id(), key, summary.changed_ns);
        }
      }
    }
  }

  void askGrid(const std::shared_ptr<core::Session>& session, Feed& feed, int64_t now_ns) {
    const uint32_t channel = feed.channels.at({Kind::kGrid, ""});
    if (!subscribed(channel) || (feed.grid_asked && feed.grid_version == feed.tile_version) ||
        now_ns - feed.grid_asked_ns < std::chrono::nanoseconds(options.grid_every).count() ||
        grids.busy(session->id())) {
      return;
    }
    feed.grid_asked = true;
    feed.grid_asked_ns = now_ns;
    feed.grid_version = feed.tile_version;
    const int64_t stamp = feed.map_changed_ns;
    grids.post(session->id(),
               [session, stamp, above = options.grid_above_m, below = options.grid_below_m] {
                 return interop::groundGrid(*session, stamp, above, below);
               });
  }

  void takeGrids() {
    for (auto& [session, grid] : grids.take()) {
      const auto feed = feeds.find(session);
      if (feed == feeds.end() || !grid) continue;  // nothing known in the band yet: no grid
      feed->second.grid = std::make_shared<const std::string>(std::move(grid->message));
      publish(feed->second.channels.at({Kind::kGrid, ""}), feed->second.map_changed_ns,
              feed->second.grid, true);
    }
  }

  // --- client messages --------------------------------------------------------------------

  static std::optional<uint32_t> uint32Of(const json& value) {
    if (!value.is_number_integer()) return std::nullopt;
    if (value.is_number_unsigned()) {
      const auto v = value.get<uint64_t>();
      if (v <= std::numeric_limits<uint32_t>::max()) return static_cast<uint32_t>(v);
      return std::nullopt;
    }
    const auto v = value.get<int64_t>();
    if (v < 0 || v > std::numeric_limits<uint32_t>::max()) return std::nullopt;
    return static_cast<uint32_t>(v);
  }

  void subscribe(Client& client, const json& message) {
    const auto list = message.find("subscriptions");
    if (list == message.end() || !list->is_array()) {
      return bad(client, "subscribe wants {\"subscriptions\": [{\"id\": N, \"channelId\": N}]}");
    }
    for (const auto& entry : *list) {
      const auto id =
          entry.is_object() && entry.contains("id") ? uint32Of(entry["id"]) : std::nullopt;
      const auto channel_id = entry.is_object() && entry.contains("channelId")
                                  ? uint32Of(entry["channelId"])
                                  : std::nullopt;
      if (!id || !channel_id) {
        bad(client, "a subscription is {\"id\": N, \"channelId\": N} (unsigned 32-bit integers)");
        continue;
      }
      if (client.subscriptions.count(*id)) {
        bad(client, "subscription " + std::to_string(*id) + " exists already");
        continue;
      }
      const auto channel = channels.find(*channel_id);
      if (channel == channels.end() || !client.advertised.count(*channel_id)) {
        bad(client, "no channel " + std::to_string(*channel_id));
        continue;
      }
      if (client.subscriptions.size() >= options.max_subscriptions) {
        bad(client, "at most " + std::to_string(options.max_subscriptions) +
                        " subscriptions per connection");
        continue;
      }
      client.subscriptions[*id] = *channel_id;
      client.by_channel[*channel_id].insert(*id);
      sendNewest(client, *id, *channel_id, channel->second);
    }
  }

  // A new subscriber's first messages: the newest of its channel.
  void sendNewest(Client& client, uint32_t sub, uint32_t channel_id, const Channel& channel) {
    const auto found = feeds.find(channel.session);
    const auto session = server.find(channel.session);
    if (found == feeds.end() || !session) return;
    Feed& feed = found->second;
    switch (channel.kind) {
      case Kind::kTf: {
        std::map<std::string, core::PoseRecord> newest;
        const size_t count = session->poseCount();
        // The newest pose of each vehicle: read from the end back (a few per vehicle).
        for (size_t end = count; end > 0 && newest.size() < feed.paths.size();) {
          const size_t begin = end > 256 ? end - 256 : 0;
          const auto poses = session->trajectory(begin, end);
          for (auto pose = poses.rbegin(); pose != poses.rend(); ++pose) {
            newest.try_emplace(pose->vehicle_id, *pose);
          }
          end = begin;
        }
        for (const auto& [vehicle, pose] : newest) {
          send(client, sub, pose.stamp_ns,
               std::make_shared<const std::string>(foxglove::frameTransform(
                   pose.stamp_ns, interop::kMapFrame, vehicle, pose.T_map_body)),
               false);
        }
        return;
      }
      case Kind::kTrajectory:
        for (const auto& [key, id] : feed.channels) {
          if (id == channel_id) {
            send(client, sub, feed.newest_stamp[key.second], pathMessage(feed, key.second), true);
          }
        }
        return;
      case Kind::kCloud:
        for (const auto& [key, id] : feed.channels) {
          if (id != channel_id) continue;
          const auto frame = feed.newest_cloud.find(key.second);
          if (frame == feed.newest_cloud.end()) return;
          const auto placed = interop::framePlacement(*session, frame->second->vehicle_id);
          if (!placed) return;
          if (auto cloud = interop::cloudMessage(*frame->second, *placed)) {
            send(client, sub, frame->second->stamp_ns,
                 std::make_shared<const std::string>(std::move(cloud->bytes)), true);
          }
        }
        return;
      case Kind::kMap: {
        const auto list = session->tiles().list();
        const uint64_t epoch = feed.level_epoch;
        chooseLevel(feed, list, session->tiles().summary().bounds);
        if (epoch != feed.level_epoch) {  // a new level: every subscriber gets every tile again
          for (auto& [id, other] : clients) {
            const auto subs = other.by_channel.find(channel_id);
            if (subs == other.by_channel.end() || &other == &client) continue;
            for (const uint32_t s : subs->second) {
              for (const auto& info : list) {
                sendTile(other, s, channel.session, info.key, feed.map_changed_ns);
              }
            }
          }
        }
        for (const auto& info : list) {
          sendTile(client, sub, channel.session, info.key, feed.map_changed_ns);
        }
        return;
      }
      case Kind::kGrid:
        if (feed.grid) send(client, sub, feed.map_changed_ns, feed.grid, true);
        return;
    }
  }

  void unsubscribe(Client& client, const json& message) {
    const auto list = message.find("subscriptionIds");
    if (list == message.end() || !list->is_array()) {
      return bad(client, "unsubscribe wants {\"subscriptionIds\": [N, ...]}");
    }
    for (const auto& entry : *list) {
      const auto id = uint32Of(entry);
      if (!id || !client.subscriptions.count(*id)) {
        bad(client, "no subscription " + entry.dump().substr(0, 40));
        continue;
      }
      dropSubscription(client, *id);
    }
  }

  void receive(Client& client, std::string_view text) {
    if (client.close) return;
    if (jsonNesting(text) > kMaxNesting) return bad(client, "message nested too deeply");
    const json message = json::parse(text, nullptr, false);
    if (message.is_discarded() || !message.is_object()) {
      return bad(client, "not a JSON object (" + std::to_string(text.size()) + " bytes)");
    }
    const auto op = message.find("op");
    if (op == message.end() || !op->is_string()) return bad(client, "a message needs \"op\"");
    const std::string name = op->get<std::string>();
    if (name == "subscribe") return subscribe(client, message);
    if (name == "unsubscribe") return unsubscribe(client, message);
    bad(client, "op '" + name.substr(0, 40) +
                    "' is not supported: this server offers subscribe and unsubscribe only");
  }

  // --- writing ----------------------------------------------------------------------------

  // A tile's blocks as SceneUpdate fields, as the tile is now (made once per version).
  const Feed::EncodedTile& encodedTile(Feed& feed, const tiles::TileSet& tiles,
                                       const tiles::TileKey& key) {
    const auto tile = tiles.find(key);
    Feed::EncodedTile& encoded = feed.encoded[key];
    const uint64_t version = tile ? tile->version() : 0;
    if (encoded.version == version && encoded.epoch == feed.level_epoch) return encoded;
    encoded = {version, feed.level_epoch, {}};
    if (!tile) return encoded;
    for (const auto& [index, entity] :
         interop::tileBlocks(*tile, feed.map_level, tiles.resolution(), feed.z_low, feed.z_span)) {
      uint64_t hash = entity.cubes.size();
      for (const auto& cube : entity.cubes) {
        for (const double v : {cube.centre.x(), cube.centre.y(), cube.centre.z(), cube.size}) {
          hash = (hash ^ std::hash<double>{}(v)) * 0x100000001b3ull;
        }
      }
      encoded.blocks[index] = {
          hash, foxglove::sceneEntityField(feed.map_changed_ns, interop::kMapFrame, entity)};
    }
    return encoded;
  }

  // What of a tile this subscription does not hold yet: its blocks that changed, deletions of
  // those that emptied. Null when nothing did.
  Text tileMessage(Client& client, const Slot& slot) {
    const auto session = server.find(slot.session);
    const auto feed = feeds.find(slot.session);
    if (!session || feed == feeds.end()) return nullptr;
    const Feed::EncodedTile& encoded = encodedTile(feed->second, session->tiles(), slot.tile);
    auto& held = client.held[{slot.subscription, slot.tile}];
    std::string update;
    for (const auto& [index, block] : encoded.blocks) {
      const auto found = held.find(index);
      if (found == held.end() || found->second != block.hash) update += block.field;
    }
    for (const auto& [index, hash] : held) {
      if (!encoded.blocks.count(index)) {
        update += foxglove::sceneDeletionField(
            static_cast<int64_t>(slot.time),
            interop::tileEntityId(slot.tile) + "/" + std::to_string(index));
      }
    }
    held.clear();
    for (const auto& [index, block] : encoded.blocks) held[index] = block.hash;
    if (held.empty()) client.held.erase({slot.subscription, slot.tile});
    if (update.empty()) return nullptr;
    return std::make_shared<const std::string>(std::move(update));
  }

  std::optional<Outgoing> next(Client& client) {
    if (!client.control.empty()) {
      auto text = std::move(client.control.front());
      client.control.pop_front();
      return Outgoing{std::move(text), false};
    }
    while (!client.data.empty()) {
      const auto slot = std::move(client.data.front());
      client.data.pop_front();
      if (!slot->key.empty()) client.pending.erase(slot->key);
      if (slot->payload) client.queued_bytes -= slot->payload->size();
      const Text payload = slot->payload ? slot->payload : tileMessage(client, *slot);
      if (!payload) continue;
      auto frame = std::make_shared<std::string>(13 + payload->size(), '\0');
      (*frame)[0] = static_cast<char>(kMessageData);
      for (int i = 0; i < 4; ++i) {
        (*frame)[1 + i] = static_cast<char>((slot->subscription >> (8 * i)) & 0xff);
      }
      for (int i = 0; i < 8; ++i)
        (*frame)[5 + i] = static_cast<char>((slot->time >> (8 * i)) & 0xff);
      std::copy(payload->begin(), payload->end(), frame->begin() + 13);
      ++stats.messages_sent;
      stats.bytes_sent += frame->size();
      return Outgoing{std::move(frame), true};
    }
    return std::nullopt;
  }
};

FoxgloveHub::FoxgloveHub(const core::MapServer& server, FoxgloveOptions options)
    : impl_(std::make_unique<Impl>(server, std::move(options))) {}

FoxgloveHub::~FoxgloveHub() = default;

FoxgloveHub::Id FoxgloveHub::connect(const std::string& session, int64_t now_ns) {
  const Id id = impl_->next_id++;
  Client& client = impl_->clients[id];
  client.scope = session;
  client.control.push_back(textOf({{"op", "serverInfo"},
                                   {"name", impl_->options.server_name},
                                   {"capabilities", json::array()},
                                   {"supportedEncodings", json::array()},
                                   {"metadata", {{"session", session}}},
                                   {"sessionId", std::to_string(impl_->hub_started_ns)}}));
  if (!session.empty() && !impl_->server.find(session)) {
    impl_->status(client, 1,
                  "session '" + session + "' is not loaded: its channels appear when it is");
  }
  impl_->channels_added = true;  // this client is told of every channel it sees
  impl_->sync(now_ns);
  return id;
}

void FoxgloveHub::disconnect(Id id) { impl_->clients.erase(id); }

void FoxgloveHub::receive(Id id, std::string_view text, int64_t /*now_ns*/) {
  const auto found = impl_->clients.find(id);
  if (found != impl_->clients.end()) impl_->receive(found->second, text);
}

void FoxgloveHub::receiveBinary(Id id, std::string_view bytes) {
  const auto found = impl_->clients.find(id);
  if (found == impl_->clients.end() || found->second.close) return;
  impl_->bad(found->second, "client publishing is not supported (got a binary message of " +
                                std::to_string(bytes.size()) + " bytes)");
}

void FoxgloveHub::poll(int64_t now_ns) {
  for (auto& [id, client] : impl_->clients) {
    if (!client.close && client.writing &&
        now_ns - client.write_started_ns >
            std::chrono::nanoseconds(impl_->options.stuck_after).count()) {
      ++impl_->stats.closed_stuck;
      impl_->closeClient(client, 1008,
                         "client stuck: a message unread for " +
                             std::to_string(impl_->options.stuck_after.count() / 1000) + " s");
    }
  }
  impl_->sync(now_ns);
}

std::optional<Outgoing> FoxgloveHub::next(Id id, int64_t now_ns) {
  const auto found = impl_->clients.find(id);
  if (found == impl_->clients.end()) return std::nullopt;
  Client& client = found->second;
  if (client.close || client.writing) return std::nullopt;
  auto message = impl_->next(client);
  if (message) {
    client.writing = true;
    client.write_started_ns = now_ns;
  }
  return message;
}

void FoxgloveHub::written(Id id) {
  const auto found = impl_->clients.find(id);
  if (found != impl_->clients.end()) found->second.writing = false;
}

std::optional<CloseOrder> FoxgloveHub::closing(Id id) const {
  const auto found = impl_->clients.find(id);
  if (found == impl_->clients.end()) return std::nullopt;
  return found->second.close;
}

FoxgloveStats FoxgloveHub::stats() const {
  FoxgloveStats stats = impl_->stats;
  stats.clients = impl_->clients.size();
  return stats;
}

}  // namespace stereomap::viewers
