// Fuzz target: OctoMap files as the server reads them (server/fusion/occupancy_map): a .bt or
// .ot imported by `stereomap-store import`, and a session's .ot snapshot restored at start-up.
// OctoMap's own reader trusts its input (it recurses as deep and reads as far as the bytes
// say), so the whole file is checked first; a hostile file must be an error, never a crash, a
// read out of bounds or an allocation without bound.
#include <sstream>
#include <string>

#include "server/fusion/occupancy_map.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace stereomap::fusion;
  const std::string bytes(reinterpret_cast<const char*>(data), size);
  {
    std::istringstream in(bytes);
    auto map = OccupancyMap::load(in);
    if (map) (*map)->occupiedCount();
  }
  {
    OccupancyMap snapshot(OccupancyMap::Options{});  // 0.1 m, as sessions default to
    std::istringstream in(bytes);
    if (!snapshot.readFull(in) && snapshot.occupiedCount() != 0) __builtin_trap();
  }
  return 0;
}
