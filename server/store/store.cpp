#include "server/store/store.hpp"

#include <fstream>

#include "common/files.hpp"

#include "server/core/exports.hpp"
#include "server/core/session_json.hpp"
#include "server/store/session_journals.hpp"

namespace stereomap::store {

namespace fs = std::filesystem;
using common::ErrorCode;
using common::makeError;

common::Result<SessionStore> SessionStore::open(const fs::path& root) {
  std::error_code ec;
  fs::create_directories(root, ec);
  if (ec || !fs::is_directory(root, ec)) {
    return makeError(ErrorCode::kIo, "cannot create the store directory " + root.string() +
                                         (ec ? ": " + ec.message() : ""));
  }
  return SessionStore(root);
}

common::Status SessionStore::probe() const {
  const fs::path probe = root_ / ".write-test";
  if (auto status = common::writeFileAtomically(probe, "ok"); !status) {
    return makeError(ErrorCode::kIo, "the store " + root_.string() + " cannot be written (" +
                                         status.error().message + ")");
  }
  std::error_code ec;
  fs::remove(probe, ec);
  return common::Ok{};
}

common::Status SessionStore::save(const core::Session& session, bool closed) const {
  const fs::path dir = root_ / session.id();  // ids are validated: no separators, no ".."
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec) return makeError(ErrorCode::kIo, "cannot create " + dir.string() + ": " + ec.message());
  const auto map = session.mapBinary();
  if (!map) return map.error();
  if (auto s = common::writeFileAtomically(dir / "map.bt", *map); !s) return s;
  const auto vehicles = session.status().vehicles;
  for (size_t i = 0; i < vehicles.size(); ++i) {  // one TUM file per vehicle
    const std::string name = i == 0 ? "trajectory.tum" : "trajectory-" + vehicles[i] + ".tum";
    if (auto s = common::writeFileAtomically(dir / name, core::trajectoryTum(session, vehicles[i]));
        !s)
      return s;
  }
  auto status = session.status();
  status.closed = closed;
  if (closed) status.read_only = false;
  return common::writeFileAtomically(dir / "session.json", core::sessionJson(status) + "\n");
}

}  // namespace stereomap::store
