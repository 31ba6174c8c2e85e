// Fuzz target: the store's session catalog as the server and stereomap-store open it
// (server/store/catalog): the input is the whole catalog.sqlite. Read-only opening lists its
// rows or fails with an error; opening it for writing sets a damaged file aside and starts a
// new catalog that can record and list a session. Rows of any values (text where numbers
// belong, NaN bounds, huge counts) must come back as rows, never a crash.
#include "server/store/catalog.hpp"
#include "tests/fuzz/fuzz_input.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace stereomap;
  const auto& dir = fuzz::scratch();
  std::filesystem::remove_all(dir.path());
  std::filesystem::create_directories(dir.path());
  dir.write("catalog.sqlite", {reinterpret_cast<const char*>(data), size});
  if (auto reader = store::Catalog::openReadOnly(dir.path())) {
    [[maybe_unused]] auto rows = (*reader)->list();  // rows or an error: both fine
  }

  auto catalog = store::Catalog::open(dir.path());
  if (!catalog) return 0;  // e.g. the damaged file could not be set aside
  core::SessionStatus status;
  status.id = "fuzz";
  if (!(*catalog)->record(status, 1)) return 0;  // a readable but unwritable file
  auto rows = (*catalog)->list();
  if (!rows) return 0;
  for (const auto& row : *rows) {
    if (row.id == "fuzz") return 0;
  }
  __builtin_trap();  // recorded, but not listed
}
