// jemalloc's options for the binaries linked with it (stereomap_use_jemalloc, CMakeLists.txt);
// MALLOC_CONF in the environment still overrides them. Read by jemalloc at its start.
//
// background_thread: jemalloc's own thread returns freed pages to the system once they have
// been unused for the decay time (10 s). Without it, an arena returns pages only when one of
// its threads allocates, so pages freed into arenas of threads that have gone quiet stay
// resident: a server with viewers kept about 200 KiB more a minute while its live heap was
// flat (docs/BENCHMARKS.md, "Soak"). Returning pages at once instead (dirty_decay_ms:0) made
// fusion 10-20 % slower; the background thread cost nothing measurable.
extern "C" {
extern const char* malloc_conf;
const char* malloc_conf = "background_thread:true";
}
