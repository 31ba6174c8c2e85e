#include "server/viewers/viewer_hub.hpp"

#include <nlohmann/json.hpp>

#include <algorithm>
#include <cmath>
#include <deque>
#include <set>
#include <utility>
#include <variant>

#include "common/keyed_worker.hpp"
#include "common/time.hpp"
#include "common/url.hpp"
#include "server/core/api.hpp"
#include "server/core/session_json.hpp"
#include "server/core/validate.hpp"
#include "server/viewers/json_nesting.hpp"
#include "server/viewers/view_planner.hpp"

namespace stereomap::viewers {

namespace {

using nlohmann::json;
using tiles::TileKey;

constexpr int kProtocol = 2;
constexpr size_t kPosesPerMessage = 2'000;  // about 1 ms of the network thread each
constexpr int kMaxNesting = 8;              // our messages nest 3 deep; deeper is hostile

using Text = std::shared_ptr<const std::string>;

Text textOf(const json& message) {
  return std::make_shared<const std::string>(
      message.dump(-1, ' ', false, json::error_handler_t::replace));
}

// A finite number from `message[name]`, or nullopt when missing; throws a message when it is
// there but wrong.
std::optional<double> number(const json& message, const char* name, double low, double high) {
  const auto found = message.find(name);
  if (found == message.end()) return std::nullopt;
  if (!found->is_number() || !std::isfinite(found->get<double>()) || found->get<double>() < low ||
      found->get<double>() > high) {
    throw std::invalid_argument(std::string("'") + name + "' must be a number in [" +
                                std::to_string(low) + ", " + std::to_string(high) + "]");
  }
  return found->get<double>();
}

std::array<double, 3> triple(const json& message, const char* name) {
  const auto found = message.find(name);
  if (found == message.end() || !found->is_array() || found->size() != 3 ||
      !std::all_of(found->begin(), found->end(),
                   [](const json& v) { return v.is_number() && std::isfinite(v.get<double>()); })) {
    throw std::invalid_argument(std::string("'") + name + "' must be [x, y, z] (finite numbers)");
  }
  return {(*found)[0].get<double>(), (*found)[1].get<double>(), (*found)[2].get<double>()};
}

// "poses" messages, one per vehicle and up to kPosesPerMessage poses, in arrival order. With
// `reset`, the first message of each vehicle not yet in it tells the viewer to replace what it
// holds of that vehicle (and the vehicle is added).
std::vector<Text> poseMessages(const std::string& session,
                               const std::vector<core::PoseRecord>& poses,
                               const std::string& only_vehicle, std::set<std::string>* reset) {
  std::map<std::string, std::vector<json>> by_vehicle;
  std::vector<std::string> order;
  for (const auto& pose : poses) {
    if (!only_vehicle.empty() && pose.vehicle_id != only_vehicle) continue;
    if (pose.held) continue;  // in a frame of its own until it joins (the lines say "aligning")
    auto [it, inserted] = by_vehicle.try_emplace(pose.vehicle_id);
    if (inserted) order.push_back(pose.vehicle_id);
    const auto& t = pose.T_map_body.translation;
    const auto& q = pose.T_map_body.rotation;
    it->second.push_back(json::array(
        {common::nsToSeconds(pose.stamp_ns), t.x(), t.y(), t.z(), q.x(), q.y(), q.z(), q.w()}));
  }
  std::vector<Text> out;
  for (const auto& vehicle : order) {
    const auto& all = by_vehicle[vehicle];
    for (size_t begin = 0; begin < all.size(); begin += kPosesPerMessage) {
      const size_t end = std::min(all.size(), begin + kPosesPerMessage);
      out.push_back(
          textOf({{"type", "poses"},
                  {"session", session},
                  {"vehicle", vehicle},
                  {"reset", reset != nullptr && reset->insert(vehicle).second},
                  {"poses", json(std::vector<json>(all.begin() + static_cast<long>(begin),
                                                   all.begin() + static_cast<long>(end)))}}));
    }
  }
  return out;
}

// Poses [next, until) of a session still to send, made into messages only when the viewer's
// queue reaches them, kPosesPerMessage at a time: a long flight's trajectory (about 110 bytes
// a pose as JSON: 24 MB for three hours of 4 vehicles at 5 Hz, and several times that while
// it is built) is never built whole, and the viewer's unsent messages hold one message of it
// at most.
struct PoseStream {
  std::weak_ptr<const core::Session> session;  // gone: the rest is dropped
  std::string session_id, only_vehicle;
  size_t from = 0, next = 0, until = 0, sent = 0;
  bool reset = false;             // each vehicle's first message replaces what the viewer holds
  std::set<std::string> started;  // vehicles whose first message has been made
  // An answer to a "trajectory" request: ends with trajectory_done (if the session lasts).
  // Otherwise a subscription's (or a correction's) poses, dropped when a newer one replaces
  // them or the viewer leaves the subscription.
  bool requested = false;

  // The next poses' messages, then trajectory_done when it is the last of a request; advances
  // `next`.
  std::vector<Text> take() {
    const auto source = session.lock();
    const size_t end = std::min(until, next + kPosesPerMessage);
    const auto poses = source ? source->trajectory(next, end) : std::vector<core::PoseRecord>{};
    const bool cut = poses.size() != end - next;  // a trajectory only grows: the session went
    next = cut ? until : end;
    auto texts = poseMessages(session_id, poses, only_vehicle, reset ? &started : nullptr);
    for (const auto& pose : poses) sent += only_vehicle.empty() || pose.vehicle_id == only_vehicle;
    if (requested && next == until && !cut) {
      texts.push_back(textOf(
          {{"type", "trajectory_done"}, {"session", session_id}, {"from", from}, {"poses", sent}}));
    }
    return texts;
  }
};

}  // namespace

struct ViewerHub::Viewer {
  bool authorised = false, greeted = false;
  int64_t connected_ns = 0;
  size_t bad_messages = 0;
  std::optional<CloseOrder> close;
  // Sent first, in order: JSON texts, live tile changes (as keys, coalesced) and poses (as
  // streams, made into texts when their turn comes).
  std::deque<std::variant<Text, TileKey, std::unique_ptr<PoseStream>>> queue;
  std::set<TileKey> queued_tiles;
  size_t queued_bytes = 0;
  // Then the current view's tiles, in plan order (coarse pass, then refinements).
  struct Planned {
    TileKey key;
    unsigned level;
    bool coarse;
  };
  std::deque<Planned> plan;
  std::optional<json> view_done;  // sent when `plan` drains
  bool writing = false;
  int64_t write_started_ns = 0;
  // The subscription.
  std::string session;
  std::optional<ViewRequest> view;
  uint64_t view_id = 0;
  unsigned coarse_level = tiles::kLevels - 1;
  // A replay (the time slider): the session as it was then, private to this viewer; null:
  // the loaded session itself. `replay_request` numbers the newest replay asked for.
  std::shared_ptr<core::Session> replay;
  uint64_t replay_request = 0;
  std::map<TileKey, unsigned> level;                      // what it should hold
  std::map<TileKey, std::pair<unsigned, uint64_t>> held;  // level and version it was sent
};

namespace {

// A replay made off the network thread (one at a time; only each viewer's newest request is
// made: a slider dragged across a flight asks for many).
struct ReplayDone {
  uint64_t request = 0;
  std::string id;
  int64_t until_ns = 0;
  common::Result<std::shared_ptr<core::Session>> session;
};

}  // namespace

// A session's pushes, shared by its subscribers.
struct ViewerHub::Feed {
  uint64_t version = 0;             // tile changes up to this version have been pushed
  size_t poses = 0;                 // poses pushed
  uint64_t trajectory_version = 0;  // of the poses pushed (a correction changes old ones)
};

struct ViewerHub::Impl {
  Impl(const core::MapServer& server, const core::SessionAdmin* admin, HubOptions options)
      : server(server), admin(admin), options(std::move(options)) {}

  const core::MapServer& server;
  const core::SessionAdmin* admin;
  const HubOptions options;
  std::map<Id, Viewer> viewers;
  Id next_id = 1;
  std::map<std::string, Feed> feeds;
  std::map<std::string, std::string> statuses;  // as last broadcast, by session
  HubStats stats;
  common::KeyedWorker<Id, ReplayDone> replays;  // by viewer

  void closeViewer(Viewer& viewer, uint16_t code, std::string reason) {
    if (viewer.close) return;
    viewer.close = CloseOrder{code, std::move(reason)};
    viewer.queue.clear();
    viewer.queued_tiles.clear();
    viewer.plan.clear();
    viewer.queued_bytes = 0;
  }

  // `bounded`: a push the viewer may fall behind on (not an answer it asked for).
  void queueText(Viewer& viewer, Text text, bool bounded = true) {
    if (viewer.close) return;
    if (bounded && viewer.queued_bytes + text->size() > options.max_queued_bytes) {
      ++stats.closed_stuck;
      return closeViewer(viewer, 1008,
                         "viewer too slow: more than " +
                             std::to_string(options.max_queued_bytes >> 20) +
                             " MB of updates unread");
    }
    viewer.queued_bytes += text->size();
    viewer.queue.emplace_back(std::move(text));
  }

  // A subscription's poses [0, until) of `session` (replacing what the viewer holds), as a
  // stream; one still queued is dropped (this one resends all it would have).
  void queuePoses(Viewer& viewer, const std::shared_ptr<const core::Session>& session,
                  size_t until) {
    dropPoseStreams(viewer);
    auto stream = std::make_unique<PoseStream>();
    stream->reset = true;
    queueStream(viewer, session, 0, until, std::move(stream));
  }

  // The answer to a "trajectory" request: poses [from, until) (of one vehicle if set), then
  // trajectory_done.
  void queueRequestedPoses(Viewer& viewer, const std::shared_ptr<const core::Session>& session,
                           size_t from, size_t until, const std::string& only_vehicle) {
    auto stream = std::make_unique<PoseStream>();
    stream->requested = true;
    stream->reset = from == 0;
    stream->only_vehicle = only_vehicle;
    queueStream(viewer, session, from, std::max(from, until), std::move(stream));
  }

  void queueStream(Viewer& viewer, const std::shared_ptr<const core::Session>& session, size_t from,
                   size_t until, std::unique_ptr<PoseStream> stream) {
    if (viewer.close || (from == until && !stream->requested)) return;
    stream->session = session;
    stream->session_id = session->id();
    stream->from = stream->next = from;
    stream->until = until;
    viewer.queue.emplace_back(std::move(stream));
  }

  // Drops the viewer's queued subscription poses (not the answers to its requests).
  static void dropPoseStreams(Viewer& viewer) {
    std::erase_if(viewer.queue, [](const auto& item) {
      const auto* stream = std::get_if<std::unique_ptr<PoseStream>>(&item);
      return stream != nullptr && !(*stream)->requested;
    });
  }

  void bad(Viewer& viewer, const std::string& message) {
    ++viewer.bad_messages;
    queueText(viewer, textOf({{"type", "error"}, {"message", message}}), false);
    if (viewer.bad_messages > options.max_bad_messages) {
      ++stats.closed_bad;
      closeViewer(viewer, 1008,
                  "too many bad messages (" + std::to_string(viewer.bad_messages) + ")");
    }
  }

  void hello(Viewer& viewer, const json& message) {
    const auto protocol = message.find("protocol");
    if (protocol == message.end() || !protocol->is_number_integer() ||
        protocol->get<int64_t>() != kProtocol) {
      ++stats.closed_bad;
      return closeViewer(viewer, 1002,
                         "this server speaks protocol 2 only: send "
                         "{\"type\": \"hello\", \"protocol\": 2}");
    }
    if (!options.access.empty() && !viewer.authorised) {
      const auto token = message.find("token");
      if (token == message.end() || !token->is_string() ||
          options.access.check(token->get<std::string>()).role == core::Role::kNone) {
        ++stats.closed_bad;
        return closeViewer(viewer, 1008, "a valid token is required (in hello or ?token=)");
      }
    }
    viewer.greeted = true;
    queueText(viewer,
              textOf({{"type", "hello"},
                      {"protocol", kProtocol},
                      {"server", options.server_name},
                      {"levels", tiles::kLevels},
                      {"tile_voxels", 1 << tiles::kTileBits}}),
              false);
    list(viewer);
  }

  void list(Viewer& viewer) {
    queueText(viewer,
              std::make_shared<const std::string>(R"({"type":"sessions","sessions":)" +
                                                  core::sessionListJson(server, admin) + "}"),
              false);
  }

  void subscribe(Viewer& viewer, const json& message) {
    const auto id = message.find("session");
    if (id == message.end() || !id->is_string() || !core::isValidId(id->get<std::string>())) {
      return bad(viewer, "subscribe wants {\"session\": ID} (1-64 of [A-Za-z0-9._-])");
    }
    const std::string session_id = id->get<std::string>();
    const auto session = server.find(session_id);
    if (!session) {
      const auto stored = admin ? admin->closedSessions() : std::vector<core::SessionStatus>{};
      const bool closed =
          std::any_of(stored.begin(), stored.end(),
                      [&](const core::SessionStatus& s) { return s.id == session_id; });
      return queueText(
          viewer,
          textOf({{"type", "error"},
                  {"code", closed ? "closed" : "not_found"},
                  {"session", session_id},
                  {"message", closed ? "session '" + session_id +
                                           "' is closed: open it first (POST /api/sessions/" +
                                           session_id + "/open)"
                                     : "no session '" + session_id + "'"}}),
          false);
    }
    unsubscribe(viewer);
    viewer.session = session_id;
    auto [feed, created] = feeds.try_emplace(session_id);
    const auto& tiles = session->tiles();
    const auto summary = tiles.summary();
    if (created) {
      feed->second.version = summary.version;
      feed->second.trajectory_version = session->trajectoryVersion();
      feed->second.poses = session->poseCount();
    }
    queueText(viewer,
              textOf({{"type", "subscribed"},
                      {"session", session_id},
                      {"resolution", tiles.resolution()},
                      {"levels", tiles::kLevels},
                      {"tile_voxels", 1 << tiles::kTileBits},
                      {"epoch", tiles.epoch()},
                      {"version", summary.version},
                      {"voxels", summary.occupied_voxels},
                      {"tiles", summary.tiles},
                      {"bounds", core::boundsJson(summary.bounds)},
                      {"status", core::sessionObject(session->status())}}),
              false);
    queuePoses(viewer, session, feed->second.poses);  // the rest comes as pushes
  }

  void unsubscribe(Viewer& viewer) {
    dropPoseStreams(viewer);
    viewer.session.clear();
    viewer.replay.reset();
    ++viewer.replay_request;  // a replay still being made is no longer wanted
    viewer.view.reset();
    viewer.level.clear();
    viewer.held.clear();
    viewer.plan.clear();
    viewer.view_done.reset();
    // Queued tiles of the old session are dropped when their turn comes (no session).
  }

  std::shared_ptr<core::Session> sessionOf(const Viewer& viewer) const {
    if (viewer.replay) return viewer.replay;
    return viewer.session.empty() ? nullptr : server.find(viewer.session);
  }

  // {"type": "replay", "session": ID, "until": SECONDS}: the session as it was then.
  void replay(Id id, Viewer& viewer, const json& message) {
    if (admin == nullptr) return bad(viewer, "replay: this server keeps no store");
    const auto session_id = message.find("session");
    if (session_id == message.end() || !session_id->is_string() ||
        !core::isValidId(session_id->get<std::string>())) {
      return bad(viewer, "replay wants {\"session\": ID, \"until\": seconds since the epoch}");
    }
    std::optional<double> until;
    try {
      until = number(message, "until", 0, 1e10);
    } catch (const std::exception& e) {
      return bad(viewer, std::string("replay: ") + e.what());
    }
    if (!until) return bad(viewer, "replay: \"until\" (seconds since the epoch) is missing");
    const uint64_t request = ++viewer.replay_request;
    replays.post(id, [admin = admin, request, session = session_id->get<std::string>(),
                      until_ns = static_cast<int64_t>(std::llround(*until * 1e9))] {
      return ReplayDone{request, session, until_ns, admin->replay(session, until_ns)};
    });
    queueText(viewer, textOf({{"type", "replaying"}, {"session", *session_id}, {"until", *until}}),
              false);
  }

  // Replays made since the last poll: each viewer switches to its newest.
  void takeReplays() {
    for (auto& [viewer_id, done] : replays.take()) {
      const auto found = viewers.find(viewer_id);
      if (found == viewers.end() || found->second.replay_request != done.request) continue;
      Viewer& viewer = found->second;
      if (!done.session) {
        queueText(viewer,
                  textOf({{"type", "error"},
                          {"code", "replay"},
                          {"session", done.id},
                          {"message", "replay: " + done.session.error().message}}),
                  false);
        continue;
      }
      const auto view = viewer.view;
      const uint64_t view_id = viewer.view_id;
      const uint64_t request = viewer.replay_request;
      unsubscribe(viewer);
      viewer.replay_request = request;
      viewer.session = done.id;
      viewer.replay = *done.session;
      const auto summary = viewer.replay->tiles().summary();
      queueText(viewer,
                textOf({{"type", "replayed"},
                        {"session", done.id},
                        {"until", static_cast<double>(done.until_ns) * 1e-9},
                        {"frames", viewer.replay->status().frames_fused},
                        {"voxels", summary.occupied_voxels},
                        {"bounds", core::boundsJson(summary.bounds)}}),
                false);
      queuePoses(viewer, viewer.replay, viewer.replay->poseCount());
      if (view) planFor(viewer, *viewer.replay, *view, view_id);
    }
  }

  void view(Viewer& viewer, const json& message) {
    if (viewer.session.empty()) return bad(viewer, "view: subscribe to a session first");
    const auto session = sessionOf(viewer);
    if (!session) return bad(viewer, "view: session '" + viewer.session + "' is gone");
    ViewRequest request;
    uint64_t view_id = 0;
    try {
      const auto eye = triple(message, "eye");
      request.eye = common::Vec3(eye[0], eye[1], eye[2]);
      if (auto fov = number(message, "fov", 1, 179)) request.fov_y_rad = *fov * M_PI / 180;
      if (auto height = number(message, "height", 1, 16384)) request.height_px = *height;
      if (auto budget = number(message, "budget", 1, static_cast<double>(options.max_budget))) {
        request.budget = static_cast<uint64_t>(*budget);
      }
      if (auto error = number(message, "error", 0.25, 64)) request.error_px = *error;
      if (auto id = number(message, "id", 0, 9e15)) view_id = static_cast<uint64_t>(*id);
      if (const auto planes = message.find("planes"); planes != message.end()) {
        if (!planes->is_array() || planes->size() > 6) {
          throw std::invalid_argument("'planes' must be up to 6 planes [a, b, c, d]");
        }
        for (const auto& plane : *planes) {
          if (!plane.is_array() || plane.size() != 4 ||
              !std::all_of(plane.begin(), plane.end(), [](const json& v) {
                return v.is_number() && std::isfinite(v.get<double>());
              })) {
            throw std::invalid_argument("'planes' must be up to 6 planes [a, b, c, d]");
          }
          request.planes.push_back({plane[0].get<double>(), plane[1].get<double>(),
                                    plane[2].get<double>(), plane[3].get<double>()});
        }
      }
    } catch (const std::exception& e) {
      return bad(viewer, std::string("view: ") + e.what());
    }
    planFor(viewer, *session, request, view_id);
  }

  // Plans `request` for the viewer and queues its tiles (replacing the rest of any earlier
  // view), announced by "plan" and closed by "view_done".
  void planFor(Viewer& viewer, const core::Session& session, const ViewRequest& request,
               uint64_t view_id) {
    const auto& tiles = session.tiles();
    const ViewPlan plan = planView(tiles.list(), tiles.resolution(), request);
    viewer.view = request;
    viewer.view_id = view_id;
    viewer.coarse_level = plan.coarse_level;
    viewer.plan.clear();
    viewer.level.clear();
    for (size_t i = plan.coarse_count; i < plan.tiles.size(); ++i) {
      viewer.level[plan.tiles[i].key] = plan.tiles[i].level;
    }
    for (size_t i = 0; i < plan.coarse_count; ++i) {
      const auto& planned = plan.tiles[i];
      const auto [final_level, _] = viewer.level.try_emplace(planned.key, plan.coarse_level);
      const auto held = viewer.held.find(planned.key);
      if (held == viewer.held.end()) viewer.plan.push_back({planned.key, plan.coarse_level, true});
      // Tiles at the coarse level that the viewer holds finer must come down to it.
      if (final_level->second == plan.coarse_level && held != viewer.held.end() &&
          held->second.first != plan.coarse_level) {
        viewer.plan.push_back({planned.key, plan.coarse_level, false});
      }
    }
    for (size_t i = plan.coarse_count; i < plan.tiles.size(); ++i) {
      viewer.plan.push_back({plan.tiles[i].key, plan.tiles[i].level, false});
    }
    // Tiles it holds that the map no longer has.
    for (const auto& [key, held] : viewer.held) {
      if (!viewer.level.count(key)) viewer.plan.push_back({key, held.first, false});
    }
    queueText(viewer,
              textOf({{"type", "plan"},
                      {"id", view_id},
                      {"session", viewer.session},
                      {"tiles", plan.tiles.size()},
                      {"cells", plan.cells},
                      {"coarse_level", plan.coarse_level},
                      {"coarse_tiles", plan.coarse_count}}),
              false);
    viewer.view_done = json{{"type", "view_done"}, {"id", view_id}, {"session", viewer.session}};
  }

  // {"type": "drop", "session": ID, "keys": ["x_y_z", ...]}: tiles the viewer no longer holds
  // (its own memory budget); they are sent again when a view needs them.
  void drop(Viewer& viewer, const json& message) {
    constexpr size_t kMaxKeys = 4096;
    const auto session = message.find("session");
    const auto keys = message.find("keys");
    if (session == message.end() || !session->is_string() || keys == message.end() ||
        !keys->is_array() || keys->size() > kMaxKeys) {
      return bad(viewer, "drop wants {\"session\": ID, \"keys\": [\"x_y_z\", ...]} (at most " +
                             std::to_string(kMaxKeys) + " keys)");
    }
    if (session->get<std::string>() != viewer.session) return;  // an old subscription's: moot
    for (const auto& text : *keys) {
      const auto key = text.is_string() ? TileKey::parse(text.get<std::string>()) : std::nullopt;
      if (!key) return bad(viewer, "drop: a key is not \"x_y_z\"");
      viewer.held.erase(*key);
      viewer.level.erase(*key);
    }
  }

  void trajectory(Viewer& viewer, const json& message) {
    std::string session_id = viewer.session;
    std::string vehicle;
    size_t from = 0;
    try {
      if (const auto s = message.find("session"); s != message.end()) {
        if (!s->is_string() || !core::isValidId(s->get<std::string>())) {
          throw std::invalid_argument("'session' must be a session id");
        }
        session_id = s->get<std::string>();
      }
      if (const auto v = message.find("vehicle"); v != message.end()) {
        if (!v->is_string() || !core::isValidId(v->get<std::string>())) {
          throw std::invalid_argument("'vehicle' must be a vehicle id");
        }
        vehicle = v->get<std::string>();
      }
      if (auto f = number(message, "from", 0, 1e12)) from = static_cast<size_t>(*f);
    } catch (const std::exception& e) {
      return bad(viewer, std::string("trajectory: ") + e.what());
    }
    const auto session = session_id == viewer.session ? sessionOf(viewer) : server.find(session_id);
    if (!session) return bad(viewer, "trajectory: no loaded session '" + session_id + "'");
    queueRequestedPoses(viewer, session, from, session->poseCount(), vehicle);
  }

  void receive(Id id, Viewer& viewer, std::string_view text) {
    if (viewer.close) return;
    if (jsonNesting(text) > kMaxNesting) return bad(viewer, "message nested too deeply");
    const json message = json::parse(text, nullptr, false);
    if (message.is_discarded() || !message.is_object()) {
      return bad(viewer, "not a JSON object (" + std::to_string(text.size()) + " bytes)");
    }
    const auto type_field = message.find("type");
    if (type_field == message.end() || !type_field->is_string()) {
      return bad(viewer, "a message needs \"type\"");
    }
    const std::string type = type_field->get<std::string>();
    if (!viewer.greeted) {
      if (type == "hello") return hello(viewer, message);
      ++stats.closed_bad;
      return closeViewer(viewer, 1008, "send {\"type\": \"hello\", \"protocol\": 2} first");
    }
    if (type == "list") return list(viewer);
    if (type == "subscribe") return subscribe(viewer, message);
    if (type == "unsubscribe") return unsubscribe(viewer);
    if (type == "view") return view(viewer, message);
    if (type == "trajectory") return trajectory(viewer, message);
    if (type == "replay") return replay(id, viewer, message);
    if (type == "drop") return drop(viewer, message);
    if (type == "ping") {
      json pong = {{"type", "pong"}};
      if (const auto t = message.find("t"); t != message.end() && t->is_number()) pong["t"] = *t;
      return queueText(viewer, textOf(pong), false);
    }
    if (type == "hello") return bad(viewer, "hello was already received");
    bad(viewer, "unknown message type '" + type.substr(0, 40) +
                    "' (hello, list, subscribe, unsubscribe, view, trajectory, ping)");
  }

  // The bytes for one tile at one level, or nullopt when there is nothing to send (it holds
  // it already, or the tile and the viewer's copy are both gone).
  std::optional<Outgoing> tileMessage(Viewer& viewer, const core::Session& session,
                                      const TileKey& key, unsigned level, bool only_if_missing) {
    const auto& tiles = session.tiles();
    const auto tile = tiles.find(key);
    const auto held = viewer.held.find(key);
    if (!tile) {  // emptied: an empty tile tells the viewer to drop it
      if (held == viewer.held.end()) return std::nullopt;
      const uint64_t version = tiles.summary().version;
      viewer.held.erase(held);
      viewer.level.erase(key);
      auto bytes = std::make_shared<const std::string>(proto::tiles::encodeTile(
          {session.id(), key, static_cast<uint8_t>(level), version, tiles.resolution()}, {}));
      return Outgoing{std::move(bytes), true};
    }
    if (held != viewer.held.end()) {
      if (held->second == std::pair{level, tile->version()}) return std::nullopt;
      if (only_if_missing && held->second.second == tile->version()) return std::nullopt;
    }
    viewer.held[key] = {level, tile->version()};
    return Outgoing{tile->encoded(level), true};
  }

  std::optional<Outgoing> next(Viewer& viewer) {
    const auto session = sessionOf(viewer);
    while (!viewer.queue.empty()) {
      auto item = std::move(viewer.queue.front());
      viewer.queue.pop_front();
      if (auto* text = std::get_if<Text>(&item)) {
        viewer.queued_bytes -= (*text)->size();
        return Outgoing{std::move(*text), false};
      }
      if (auto* pending = std::get_if<std::unique_ptr<PoseStream>>(&item)) {
        PoseStream& stream = **pending;
        auto texts = stream.take();
        if (stream.next < stream.until) viewer.queue.push_front(std::move(item));  // stays first
        for (auto text = texts.rbegin(); text != texts.rend(); ++text) {
          viewer.queued_bytes += (*text)->size();
          viewer.queue.push_front(std::move(*text));
        }
        continue;
      }
      const TileKey key = std::get<TileKey>(item);
      viewer.queued_tiles.erase(key);
      if (!session) continue;
      const auto level = viewer.level.find(key);
      if (level == viewer.level.end()) continue;
      if (auto message = tileMessage(viewer, *session, key, level->second, false)) return message;
    }
    while (session && !viewer.plan.empty()) {
      const auto planned = viewer.plan.front();
      viewer.plan.pop_front();
      if (auto message =
              tileMessage(viewer, *session, planned.key, planned.level, planned.coarse)) {
        return message;
      }
    }
    if (viewer.view_done && viewer.plan.empty()) {
      auto done = textOf(*viewer.view_done);
      viewer.view_done.reset();
      return Outgoing{std::move(done), false};
    }
    return std::nullopt;
  }

  // Sessions' statuses to every viewer; removed sessions too.
  void pushStatuses() {
    std::map<std::string, std::string> now;
    for (const auto& session : server.sessions()) {
      now[session->id()] = core::sessionJson(session->status(), "session");
    }
    std::vector<Text> out;
    for (const auto& [id, _] : statuses) {
      if (!now.count(id)) out.push_back(textOf({{"type", "session_removed"}, {"id", id}}));
    }
    for (const auto& [id, text] : now) {
      const auto before = statuses.find(id);
      if (before == statuses.end() || before->second != text) {
        out.push_back(std::make_shared<const std::string>(text));
      }
    }
    statuses = std::move(now);
    if (out.empty()) return;
    for (auto& [id, viewer] : viewers) {
      if (!viewer.greeted) continue;
      for (const auto& text : out) queueText(viewer, text);
    }
  }

  // Each subscribed session's changed tiles and new poses to its subscribers.
  void pushFeeds() {
    std::map<std::string, std::vector<Viewer*>> subscribers;
    for (auto& [id, viewer] : viewers) {
      if (!viewer.session.empty() && !viewer.close && !viewer.replay) {
        subscribers[viewer.session].push_back(&viewer);
      }
    }
    for (auto feed = feeds.begin(); feed != feeds.end();) {
      const auto session = server.find(feed->first);
      if (!session || !subscribers.count(feed->first)) {
        feed = feeds.erase(feed);
        continue;
      }
      const auto& tiles = session->tiles();
      auto changed = tiles.changedSince(feed->second.version);
      if (!changed) {  // too far behind: every tile may have changed
        changed.emplace();
        for (const auto& info : tiles.list()) changed->emplace_back(info.key, info.version);
      }
      if (!changed->empty()) {
        for (const auto& [key, version] : *changed) {
          feed->second.version = std::max(feed->second.version, version);
        }
        const auto summary = tiles.summary();
        feed->second.version = std::max(feed->second.version, summary.version);
        const Text marker = textOf({{"type", "map"},
                                    {"session", feed->first},
                                    {"version", feed->second.version},
                                    {"changed_ms", static_cast<double>(summary.changed_ns) * 1e-6},
                                    {"voxels", summary.occupied_voxels},
                                    {"tiles", summary.tiles},
                                    {"bounds", core::boundsJson(summary.bounds)}});
        for (Viewer* viewer : subscribers[feed->first]) {
          if (!viewer->view) continue;  // its first view will fetch everything
          for (const auto& [key, version] : *changed) {
            auto level = viewer->level.find(key);
            if (level == viewer->level.end()) {
              if (!tiles.find(key)) continue;  // appeared and went: nothing to show
              level = viewer->level
                          .emplace(key, levelFor(key, tiles.resolution(), *viewer->view,
                                                 viewer->coarse_level))
                          .first;
            }
            if (viewer->queued_tiles.insert(key).second) viewer->queue.emplace_back(key);
          }
          queueText(*viewer, marker);
        }
      }
      // A pose correction changed poses already pushed: every pose again, replacing them (a
      // stream: a long flight's would pass the cap on unsent pushes).
      const uint64_t trajectory_version = session->trajectoryVersion();
      if (trajectory_version != feed->second.trajectory_version) {
        feed->second.trajectory_version = trajectory_version;
        feed->second.poses = session->poseCount();
        for (Viewer* viewer : subscribers[feed->first]) {
          queuePoses(*viewer, session, feed->second.poses);
        }
      }
      const auto poses = session->trajectory(feed->second.poses);
      if (!poses.empty()) {
        feed->second.poses += poses.size();
        const auto messages = poseMessages(feed->first, poses, "", nullptr);
        for (Viewer* viewer : subscribers[feed->first]) {
          for (const auto& text : messages) queueText(*viewer, text);
        }
      }
      ++feed;
    }
  }
};

ViewerHub::ViewerHub(const core::MapServer& server, const core::SessionAdmin* admin,
                     HubOptions options)
    : impl_(std::make_unique<Impl>(server, admin, std::move(options))) {}

ViewerHub::~ViewerHub() = default;

ViewerHub::Id ViewerHub::connect(bool authorised, int64_t now_ns) {
  const Id id = impl_->next_id++;
  Viewer& viewer = impl_->viewers[id];
  viewer.authorised = authorised || impl_->options.access.empty();
  viewer.connected_ns = now_ns;
  return id;
}

void ViewerHub::disconnect(Id id) { impl_->viewers.erase(id); }

void ViewerHub::receive(Id id, std::string_view text, int64_t /*now_ns*/) {
  const auto found = impl_->viewers.find(id);
  if (found != impl_->viewers.end()) impl_->receive(id, found->second, text);
}

void ViewerHub::receiveBinary(Id id, std::string_view bytes) {
  const auto found = impl_->viewers.find(id);
  if (found == impl_->viewers.end()) return;
  impl_->bad(found->second, "binary messages are not part of protocol 2 (got " +
                                std::to_string(bytes.size()) + " bytes)");
}

void ViewerHub::poll(int64_t now_ns) {
  const auto& options = impl_->options;
  for (auto& [id, viewer] : impl_->viewers) {
    if (viewer.close) continue;
    if (!viewer.greeted &&
        now_ns - viewer.connected_ns > std::chrono::nanoseconds(options.hello_within).count()) {
      ++impl_->stats.closed_bad;
      impl_->closeViewer(
          viewer, 1008,
          "no hello within " + std::to_string(options.hello_within.count() / 1000) + " s");
    } else if (viewer.writing && now_ns - viewer.write_started_ns >
                                     std::chrono::nanoseconds(options.stuck_after).count()) {
      ++impl_->stats.closed_stuck;
      impl_->closeViewer(viewer, 1008,
                         "viewer stuck: a message unread for " +
                             std::to_string(options.stuck_after.count() / 1000) + " s");
    }
  }
  impl_->takeReplays();
  impl_->pushStatuses();
  impl_->pushFeeds();
}

std::optional<Outgoing> ViewerHub::next(Id id, int64_t now_ns) {
  const auto found = impl_->viewers.find(id);
  if (found == impl_->viewers.end()) return std::nullopt;
  Viewer& viewer = found->second;
  if (viewer.close || viewer.writing) return std::nullopt;
  auto message = impl_->next(viewer);
  if (message) {
    viewer.writing = true;
    viewer.write_started_ns = now_ns;
    ++impl_->stats.messages_sent;
    if (message->binary) {
      ++impl_->stats.tiles_sent;
      impl_->stats.tile_bytes_sent += message->bytes->size();
    }
  }
  return message;
}

void ViewerHub::written(Id id) {
  const auto found = impl_->viewers.find(id);
  if (found != impl_->viewers.end()) found->second.writing = false;
}

std::optional<CloseOrder> ViewerHub::closing(Id id) const {
  const auto found = impl_->viewers.find(id);
  if (found == impl_->viewers.end()) return std::nullopt;
  return found->second.close;
}

std::vector<ViewerHub::Id> ViewerHub::ids() const {
  std::vector<Id> out;
  for (const auto& [id, _] : impl_->viewers) out.push_back(id);
  return out;
}

HubStats ViewerHub::stats() const {
  HubStats stats = impl_->stats;
  stats.viewers = impl_->viewers.size();
  return stats;
}

}  // namespace stereomap::viewers
