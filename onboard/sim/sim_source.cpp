#include "onboard/sim/sim_source.hpp"

#include <cmath>
#include <sstream>

#include "common/time.hpp"

namespace stereomap::sim {

SimSource::SimSource(const SimSourceOptions& options)
    : options_(options),
      scene_(Scene::makeRoom(
          {.seed = options.seed, .length = options.room_length, .width = options.room_width})),
      flight_(options.flight),
      renderer_(scene_, camera_, options.render) {}

std::optional<camera::SourceFrame> SimSource::next() {
  if (options_.max_frames != 0 && index_ >= options_.max_frames) return std::nullopt;
  // The clock starts with the first frame taken, as a camera's does: a vehicle that first
  // waits for its server must not stamp its frames as that much older.
  if (options_.start_stamp_ns == 0) options_.start_stamp_ns = common::nowNs();
  const double since_start_s = static_cast<double>(index_) / options_.rate_hz;
  const double t_s = options_.start_s + since_start_s;
  camera::SourceFrame frame;
  frame.index = index_++;
  frame.stamp_ns =
      options_.start_stamp_ns + static_cast<int64_t>(std::llround(since_start_s * 1e9));
  frame.T_map_body = flight_.T_map_body(t_s);
  frame.T_body_camera = flight_.T_body_camera();
  const double half_exposure = 0.5 * options_.render.camera.exposure_s;
  StereoFrame rendered =
      renderer_.render(*frame.T_map_body * *frame.T_body_camera,
                       Renderer::Exposure{flight_.T_map_camera(t_s - half_exposure),
                                          flight_.T_map_camera(t_s + half_exposure)});
  frame.left = std::move(rendered.left);
  frame.right = std::move(rendered.right);
  return frame;
}

std::string SimSource::describe() const {
  std::ostringstream out;
  const auto bounds = scene_.bounds();
  out << "sim (seed " << options_.seed << ", " << scene_.boxes().size() << " boxes in "
      << bounds.max.x() - bounds.min.x() << " x " << bounds.max.y() - bounds.min.y()
      << " m, loop of " << flight_.options().period_s << " s, " << camera_.width << "x"
      << camera_.height << ")";
  return out.str();
}

}  // namespace stereomap::sim
