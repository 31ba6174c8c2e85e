// What alignMaps() answers, as the CLI's and the REST answer's line: shared by the build
// with Open3D and the one without (map_align_unavailable.cpp).
#include <cstdio>

#include "server/align/map_align.hpp"

namespace stereomap::align {

std::string alignLine(const std::string& a, const std::string& b, const Alignment& alignment) {
  char text[512];
  if (!alignment.found) {
    std::snprintf(text, sizeof(text), "align %s %s: none (%s)", a.c_str(), b.c_str(),
                  alignment.reason.c_str());
    return text;
  }
  common::Quat q = alignment.T_a_b.rotation.normalized();
  if (q.w() < 0) q.coeffs() = -q.coeffs();  // one of the two quaternions of a rotation
  const common::Vec3& t = alignment.T_a_b.translation;
  std::snprintf(text, sizeof(text),
                "align %s %s: t %.4f %.4f %.4f q %.6f %.6f %.6f %.6f, overlap %.0f%%, rmse %.4f "
                "m, %.1f s",
                a.c_str(), b.c_str(), t.x(), t.y(), t.z(), q.x(), q.y(), q.z(), q.w(),
                100 * alignment.overlap, alignment.rmse_m, alignment.seconds);
  return text;
}

}  // namespace stereomap::align
