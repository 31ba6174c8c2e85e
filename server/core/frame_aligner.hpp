// Vehicles that fly in their own frame (proto::VehicleFrame::kOwn) joined into their session's:
// a thread of the server's that, for every held vehicle whose map has grown enough
// (Session::alignmentsDue), aligns that map with the session's (server/align) and, once two
// attempts on a growing map agree, has the MapServer journal and join it. A vehicle whose map
// never overlaps the session's is never joined: a wrong alignment is worse than none.
//
//   core::FrameAligner aligner(server, {});   // runs until destroyed
#pragma once

#include <chrono>
#include <condition_variable>
#include <mutex>
#include <string>
#include <thread>

#include "server/align/map_align.hpp"
#include "server/core/map_server.hpp"

namespace stereomap::core {

class FrameAligner {
 public:
  struct Options {
    std::chrono::milliseconds every{500};  // how often sessions are looked at
    // Two attempts agree when their poses are this close: translation in voxels of the
    // session's map, rotation in degrees.
    double agree_voxels = 1.0;
    double agree_deg = 0.5;
    // One thread: the aligner is background work beside fusion. Without the wider matches:
    // a vehicle of another place is refused in half the time, and the vehicle that overlaps
    // gets its confirming attempt before its flight ends (a loaded test run missed it).
    align::AlignOptions align{.wider_matches = false};
  };
  FrameAligner(MapServer& server, Options options);
  ~FrameAligner();
  FrameAligner(const FrameAligner&) = delete;
  FrameAligner& operator=(const FrameAligner&) = delete;

  // One attempt for a held vehicle of a session (what the thread does): true when it joined.
  bool attempt(Session& session, const std::string& vehicle);

 private:
  void run();

  MapServer& server_;
  const Options options_;
  std::mutex mutex_;
  std::condition_variable stop_changed_;
  bool stopping_ = false;
  std::thread thread_;
};

}  // namespace stereomap::core
