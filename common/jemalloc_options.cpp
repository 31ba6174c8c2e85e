// jemalloc's options for the binaries linked with it (stereomap_use_jemalloc, CMakeLists.txt);
// MALLOC_CONF in the environment still overrides them. Read by jemalloc at its start.
//
// background_thread: jemalloc's own threads return freed pages to the system once they have
// been unused for the decay time (10 s), whatever the process's threads are doing; without
// them the purge runs only inside the process's own allocations and frees. Measured in the
// soak (4 vehicles, 5 viewers, ~10 min, docs/BENCHMARKS.md "Soak"): RSS grew 6 % with the
// default and with a 1 s decay, 1.5 % with background threads, while the live heap stayed
// flat. Returning pages at once (dirty_decay_ms:0) also held RSS, but made each frame 10-20 %
// slower in stereomap-bench-scale; the background threads cost nothing measurable there.
extern "C" {
extern const char* malloc_conf;
const char* malloc_conf = "background_thread:true";
}
