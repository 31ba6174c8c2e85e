// The allocator's own account of this process's heap, when the allocator is jemalloc (the
// server's and stereomap-store's; CMakeLists.txt): what is live, and what it keeps in memory.
// The difference is pages the allocator holds for reuse, which RSS alone cannot tell apart
// from a leak.
#pragma once

#include <cstddef>
#include <optional>

namespace stereomap::common {

struct HeapStats {
  size_t allocated = 0;  // bytes handed out and not yet freed
  size_t resident = 0;   // at most this many bytes of the allocator's pages are in memory
  // Whether jemalloc's own threads return freed pages (common/jemalloc_options.cpp asks for
  // it; a misspelt option would be ignored without a word).
  bool background_thread = false;
};

// Fresh figures; empty when the process does not run on jemalloc (sanitizer builds, tests).
std::optional<HeapStats> heapStats();

}  // namespace stereomap::common
