// Replays a fuzz target's committed corpus (every file under the directories given) through
// LLVMFuzzerTestOneInput, so that an ordinary build re-checks every input that once found a
// problem: a crash fails the test, and so does asking for more than 4 GiB (the address space
// is limited, so such an allocation throws instead of filling the machine's memory).
// libFuzzer's own driver replaces this main in fuzz builds.
#include <sys/resource.h>

#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <vector>

#if defined(__has_feature)
#define STEREOMAP_HAS_SANITIZER \
  (__has_feature(address_sanitizer) || __has_feature(thread_sanitizer))
#else
#define STEREOMAP_HAS_SANITIZER 0
#endif

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size);

int main(int argc, char** argv) {
#if !defined(__SANITIZE_ADDRESS__) && !defined(__SANITIZE_THREAD__) && !STEREOMAP_HAS_SANITIZER
  // (The address and thread sanitizers reserve far more address space than this for shadow
  // memory.)
  const rlimit limit{4ull << 30, 4ull << 30};
  ::setrlimit(RLIMIT_AS, &limit);
#endif
  size_t replayed = 0;
  for (int i = 1; i < argc; ++i) {
    if (!std::filesystem::is_directory(argv[i])) {
      std::fprintf(stderr, "replay: %s is not a directory\n", argv[i]);
      return 2;
    }
    for (const auto& entry : std::filesystem::recursive_directory_iterator(argv[i])) {
      if (!entry.is_regular_file()) continue;
      std::ifstream in(entry.path(), std::ios::binary);
      const std::vector<uint8_t> bytes((std::istreambuf_iterator<char>(in)), {});
      LLVMFuzzerTestOneInput(bytes.data(), bytes.size());
      ++replayed;
    }
  }
  std::printf("replay: %zu inputs, no crash\n", replayed);
  return replayed > 0 ? 0 : 1;
}
