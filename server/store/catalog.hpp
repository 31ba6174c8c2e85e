// The store's session catalog: one SQLite row per session (id, vehicles, state, frames,
// resolution, occupied voxels, bounds, journal size, last update), so that tools can list
// what a store holds without replaying journals. The journals stay the source of truth: a
// damaged catalog is set aside (renamed *.corrupt-<time>) and rebuilt from the sessions.
#pragma once

#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "common/result.hpp"
#include "server/core/session.hpp"

namespace stereomap::store {

struct CatalogRow {
  std::string id;
  std::string vehicles;  // comma-separated, in order of appearance
  std::string state;     // live | ended | opened | closed (core::stateName)
  uint64_t frames = 0;
  double resolution = 0;
  uint64_t occupied_voxels = 0;
  common::Box3 bounds;
  uint64_t journal_bytes = 0;
  int64_t updated_ns = 0;
};

// A session's row as record() stores it (updated_ns left for the caller).
CatalogRow catalogRow(const core::SessionStatus& status, uint64_t journal_bytes);
// The status a row keeps (core::SessionFields::kCatalog): id, vehicles, state, frames,
// resolution, occupied voxels and bounds; the rest at its defaults.
core::SessionStatus catalogStatus(const CatalogRow& row);

class Catalog {
 public:
  // Opens (or creates) <root>/catalog.sqlite. A file that is not a healthy SQLite database
  // is renamed aside and a new catalog started; `warning()` then says so.
  static common::Result<std::unique_ptr<Catalog>> open(const std::filesystem::path& root);
  ~Catalog();

  // Opens an existing catalog for reading only (tools beside a running server); never
  // changes the file.
  static common::Result<std::unique_ptr<Catalog>> openReadOnly(const std::filesystem::path& root);

  common::Status record(const core::SessionStatus& status, uint64_t journal_bytes);
  common::Status remove(const std::string& id);
  common::Result<std::vector<CatalogRow>> list() const;
  const std::string& warning() const { return warning_; }

 private:
  struct Impl;
  explicit Catalog(std::unique_ptr<Impl> impl);
  // Opens the database and checks it is whole; throws SQLite::Exception when it is not.
  static std::unique_ptr<Impl> openHealthy(const std::filesystem::path& path);
  std::unique_ptr<Impl> impl_;
  std::string warning_;
};

}  // namespace stereomap::store
