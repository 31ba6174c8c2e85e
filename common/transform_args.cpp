#include "common/transform_args.hpp"

namespace stereomap::common {

std::optional<Rigid3> rigidFromTxyzQxyzw(const std::vector<double>& v) {
  if (v.size() != 7) return std::nullopt;
  const Quat q(v[6], v[3], v[4], v[5]);
  const Vec3 t(v[0], v[1], v[2]);
  if (!t.allFinite() || !isUnitQuaternion(q)) return std::nullopt;
  return Rigid3{q.normalized(), t};
}

}  // namespace stereomap::common
