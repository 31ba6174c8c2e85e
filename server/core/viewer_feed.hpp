// What the server pushes to browser viewers (docs/PROTOCOL.md): session statuses, occupied
// voxels as changes between snapshots, and trajectory poses as they are appended. One diff
// per session serves every viewer; a new viewer gets the full state as of the last poll.
// Not thread-safe: the network thread owns it.
#pragma once

#include <map>
#include <memory>
#include <string>
#include <vector>

#include "server/core/map_server.hpp"

namespace stereomap::core {

class ViewerFeed {
 public:
  explicit ViewerFeed(const MapServer& server);
  // Messages for a viewer that just connected (hello + the state as of the last poll()).
  std::vector<std::string> welcome() const;
  // Changes since the previous poll(), to send to every connected viewer.
  std::vector<std::string> poll();

 private:
  struct SessionState {
    std::map<tiles::TileKey, std::shared_ptr<const tiles::Tile>> tiles;  // as sent
    uint64_t version = 0;                                                // of the tiles as sent
    double resolution = 0;
    size_t occupied = 0;
    size_t poses_sent = 0;
    std::string status_json;
  };
  const MapServer& server_;
  std::map<std::string, SessionState> sessions_;
  std::vector<std::string> order_;
};

}  // namespace stereomap::core
