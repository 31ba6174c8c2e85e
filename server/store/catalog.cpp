#include "server/store/catalog.hpp"

#include <SQLiteCpp/SQLiteCpp.h>
#include <sqlite3.h>

#include <algorithm>

#include "common/time.hpp"

namespace stereomap::store {

namespace fs = std::filesystem;
using common::ErrorCode;
using common::makeError;

struct Catalog::Impl {
  explicit Impl(const fs::path& path, int flags = SQLite::OPEN_READWRITE | SQLite::OPEN_CREATE)
      : db(path.string(), flags) {}
  SQLite::Database db;
};

namespace {

constexpr const char* kSchema = R"(
CREATE TABLE IF NOT EXISTS sessions (
  id TEXT PRIMARY KEY,
  vehicles TEXT NOT NULL,
  state TEXT NOT NULL,
  frames INTEGER NOT NULL,
  resolution REAL NOT NULL,
  occupied_voxels INTEGER NOT NULL,
  min_x REAL, min_y REAL, min_z REAL, max_x REAL, max_y REAL, max_z REAL,
  journal_bytes INTEGER NOT NULL,
  updated_ns INTEGER NOT NULL
))";

}  // namespace

std::unique_ptr<Catalog::Impl> Catalog::openHealthy(const fs::path& path) {
  auto impl = std::make_unique<Catalog::Impl>(path);
  impl->db.exec("PRAGMA journal_mode=WAL");
  const std::string check = impl->db.execAndGet("PRAGMA integrity_check").getString();
  if (check != "ok") throw SQLite::Exception("integrity check: " + check);
  impl->db.exec(kSchema);
  return impl;
}

Catalog::Catalog(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Catalog::~Catalog() = default;

common::Result<std::unique_ptr<Catalog>> Catalog::open(const fs::path& root) {
  const fs::path path = root / "catalog.sqlite";
  std::string warning;
  std::unique_ptr<Impl> impl;
  try {
    impl = openHealthy(path);
  } catch (const SQLite::Exception& e) {
    // A full or failing disk is not damage: leave the file alone and say why.
    const int code = e.getErrorCode() & 0xFF;  // the primary result code
    if (code == SQLITE_FULL || code == SQLITE_IOERR || code == SQLITE_READONLY ||
        code == SQLITE_CANTOPEN || code == SQLITE_BUSY || code == SQLITE_LOCKED) {
      return makeError(ErrorCode::kIo, path.string() + ": cannot open the catalog: " + e.what());
    }
    // The journals hold the truth: keep the damaged file for inspection, start afresh.
    const fs::path aside =
        path.string() + ".corrupt-" + std::to_string(common::nowNs() / 1'000'000'000);
    std::error_code ec;
    fs::rename(path, aside, ec);
    for (const char* suffix : {"-wal", "-shm"}) fs::remove(path.string() + suffix, ec);
    warning = path.string() + " was damaged (" + e.what() + "); moved to " + aside.string() +
              " and rebuilt from the session journals";
    try {
      impl = openHealthy(path);
    } catch (const SQLite::Exception& again) {
      return makeError(ErrorCode::kIo,
                       path.string() + ": cannot create the catalog: " + again.what());
    }
  }
  auto catalog = std::unique_ptr<Catalog>(new Catalog(std::move(impl)));
  catalog->warning_ = std::move(warning);
  return catalog;
}

common::Result<std::unique_ptr<Catalog>> Catalog::openReadOnly(const fs::path& root) {
  const fs::path path = root / "catalog.sqlite";
  try {
    auto impl = std::make_unique<Impl>(path, SQLite::OPEN_READONLY);
    impl->db.execAndGet("SELECT COUNT(*) FROM sessions");
    return std::unique_ptr<Catalog>(new Catalog(std::move(impl)));
  } catch (const SQLite::Exception& e) {
    return makeError(ErrorCode::kIo, path.string() + ": cannot read the catalog: " + e.what());
  }
}

common::Status Catalog::remove(const std::string& id) {
  try {
    SQLite::Statement erase(impl_->db, "DELETE FROM sessions WHERE id = ?");
    erase.bind(1, id);
    erase.exec();
  } catch (const SQLite::Exception& e) {
    return makeError(ErrorCode::kIo, "catalog: cannot remove session '" + id + "': " + e.what());
  }
  return common::Ok{};
}

CatalogRow catalogRow(const core::SessionStatus& s, uint64_t journal_bytes) {
  CatalogRow row{s.id,
                 "",
                 core::stateName(s),
                 s.frames_fused,
                 s.resolution,
                 s.occupied_voxels,
                 s.bounds,
                 journal_bytes,
                 0};
  for (const auto& v : s.vehicles) row.vehicles += (row.vehicles.empty() ? "" : ",") + v;
  return row;
}

core::SessionStatus catalogStatus(const CatalogRow& row) {
  core::SessionStatus s;
  s.id = row.id;
  for (size_t start = 0; start < row.vehicles.size();) {
    const size_t comma = std::min(row.vehicles.find(',', start), row.vehicles.size());
    if (comma > start) s.vehicles.push_back(row.vehicles.substr(start, comma - start));
    start = comma + 1;
  }
  s.closed = row.state == "closed";
  s.read_only = row.state == "opened";
  s.ended = row.state != "live";
  s.frames_fused = s.frames_received = row.frames;
  s.resolution = row.resolution;
  s.occupied_voxels = row.occupied_voxels;
  s.bounds = row.bounds;
  return s;
}

common::Status Catalog::record(const core::SessionStatus& s, uint64_t journal_bytes) {
  const CatalogRow row = catalogRow(s, journal_bytes);
  try {
    SQLite::Statement upsert(impl_->db, R"(
      INSERT INTO sessions VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)
      ON CONFLICT(id) DO UPDATE SET vehicles = excluded.vehicles, state = excluded.state,
        frames = excluded.frames, resolution = excluded.resolution,
        occupied_voxels = excluded.occupied_voxels, min_x = excluded.min_x,
        min_y = excluded.min_y, min_z = excluded.min_z, max_x = excluded.max_x,
        max_y = excluded.max_y, max_z = excluded.max_z, journal_bytes = excluded.journal_bytes,
        updated_ns = excluded.updated_ns)");
    upsert.bind(1, row.id);
    upsert.bind(2, row.vehicles);
    upsert.bind(3, row.state);
    upsert.bind(4, static_cast<int64_t>(row.frames));
    upsert.bind(5, row.resolution);
    upsert.bind(6, static_cast<int64_t>(row.occupied_voxels));
    for (int i = 0; i < 3; ++i) {
      if (row.bounds.empty()) {
        upsert.bind(7 + i);
        upsert.bind(10 + i);
      } else {
        upsert.bind(7 + i, row.bounds.min[i]);
        upsert.bind(10 + i, row.bounds.max[i]);
      }
    }
    upsert.bind(13, static_cast<int64_t>(row.journal_bytes));
    upsert.bind(14, static_cast<int64_t>(common::nowNs()));
    upsert.exec();
  } catch (const SQLite::Exception& e) {
    return makeError(ErrorCode::kIo,
                     std::string("catalog: cannot record session '") + s.id + "': " + e.what());
  }
  return common::Ok{};
}

common::Result<std::vector<CatalogRow>> Catalog::list() const {
  std::vector<CatalogRow> rows;
  try {
    SQLite::Statement query(impl_->db, "SELECT * FROM sessions ORDER BY updated_ns");
    while (query.executeStep()) {
      CatalogRow row;
      row.id = query.getColumn(0).getString();
      row.vehicles = query.getColumn(1).getString();
      row.state = query.getColumn(2).getString();
      row.frames = static_cast<uint64_t>(query.getColumn(3).getInt64());
      row.resolution = query.getColumn(4).getDouble();
      row.occupied_voxels = static_cast<uint64_t>(query.getColumn(5).getInt64());
      if (!query.getColumn(6).isNull()) {
        row.bounds.extend({query.getColumn(6).getDouble(), query.getColumn(7).getDouble(),
                           query.getColumn(8).getDouble()});
        row.bounds.extend({query.getColumn(9).getDouble(), query.getColumn(10).getDouble(),
                           query.getColumn(11).getDouble()});
      }
      row.journal_bytes = static_cast<uint64_t>(query.getColumn(12).getInt64());
      row.updated_ns = query.getColumn(13).getInt64();
      rows.push_back(std::move(row));
    }
  } catch (const SQLite::Exception& e) {
    return makeError(ErrorCode::kIo, std::string("catalog: cannot list sessions: ") + e.what());
  }
  return rows;
}

}  // namespace stereomap::store
