#include "onboard/sim/surface_shader.hpp"

namespace stereomap::sim {

using common::Vec3;

namespace {

// Even-odd rule.
bool insidePolygon(const std::vector<Eigen::Vector2d>& polygon, double x, double y) {
  bool inside = false;
  for (size_t i = 0, j = polygon.size() - 1; i < polygon.size(); j = i++) {
    const Eigen::Vector2d& a = polygon[i];
    const Eigen::Vector2d& b = polygon[j];
    if ((a.y() > y) != (b.y() > y) && x < (b.x() - a.x()) * (y - a.y()) / (b.y() - a.y()) + a.x())
      inside = !inside;
  }
  return inside;
}

}  // namespace

SurfaceShader::SurfaceShader(const Scene& scene)
    : scene_(scene), paint_bounds_(scene.boxes_.size()) {  // empty: no paint
  for (size_t i = 0; i < scene.markings_.size(); ++i) {
    const int box = scene.markings_[i].box;
    if (box >= 0 && static_cast<size_t>(box) < paint_bounds_.size())
      paint_bounds_[box].extend(scene.marking_bounds_[i]);
  }
}

void SurfaceShader::paint(int box, const Vec3& p, float& albedo, float& shade) const {
  for (size_t i = 0; i < scene_.markings_.size(); ++i) {
    const SceneMarking& marking = scene_.markings_[i];
    if (marking.box == box && scene_.marking_bounds_[i].contains(Eigen::Vector2d(p.x(), p.y())) &&
        insidePolygon(marking.polygon, p.x(), p.y())) {
      if (marking.shade) {
        shade *= marking.albedo;
      } else {
        albedo = marking.albedo;
      }
    }
  }
}

}  // namespace stereomap::sim
