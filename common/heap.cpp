#include "common/heap.hpp"

#include <cstdint>

// jemalloc's control interface, declared weak: the symbol is null unless the process is
// linked with jemalloc, so that every binary can ask without depending on it.
extern "C" int mallctl(const char* name, void* old_value, size_t* old_size, void* new_value,
                       size_t new_size) __attribute__((weak));

namespace stereomap::common {

std::optional<HeapStats> heapStats() {
  if (mallctl == nullptr) return std::nullopt;
  // The statistics are a snapshot taken when the epoch is advanced.
  uint64_t epoch = 1;
  size_t size = sizeof(epoch);
  if (mallctl("epoch", &epoch, &size, &epoch, size) != 0) return std::nullopt;
  HeapStats stats;
  size = sizeof(size_t);
  if (mallctl("stats.allocated", &stats.allocated, &size, nullptr, 0) != 0 ||
      mallctl("stats.resident", &stats.resident, &size, nullptr, 0) != 0) {
    return std::nullopt;
  }
  size = sizeof(stats.background_thread);
  if (mallctl("opt.background_thread", &stats.background_thread, &size, nullptr, 0) != 0) {
    return std::nullopt;
  }
  return stats;
}

}  // namespace stereomap::common
