#include "onboard/sim/renderer.hpp"

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <cstring>
#include <functional>
#include <limits>
#include <memory>

#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>

#include <random>

#include "common/statistics.hpp"
#include "onboard/sim/detail/lanes.hpp"
#include "onboard/sim/surface_shader.hpp"

namespace stereomap::sim {

using common::Rigid3;
using common::Vec3;

Renderer::Renderer(const Scene& scene, camera::StereoCamera camera, RenderOptions options)
    : scene_(scene), camera_(camera), options_(options) {}

namespace {

// The image rows/columns a box can cover, within `bounds` (conservative: all of `bounds` when
// any corner is behind the camera). Pixels outside it need no intersection test with that box.
cv::Rect projectedRect(const SceneBox& box, const Rigid3& T_camera_map,
                       const camera::StereoCamera& camera, const cv::Rect& bounds) {
  double u_min = 1e9, u_max = -1e9, v_min = 1e9, v_max = -1e9;
  for (int corner = 0; corner < 8; ++corner) {
    const Vec3 p = T_camera_map * box.corner(corner);
    if (p.z() < 1e-3) return bounds;
    const auto uv = camera.project(p);
    u_min = std::min(u_min, uv->x());
    u_max = std::max(u_max, uv->x());
    v_min = std::min(v_min, uv->y());
    v_max = std::max(v_max, uv->y());
  }
  const cv::Rect rect(
      cv::Point(static_cast<int>(std::floor(u_min)) - 1, static_cast<int>(std::floor(v_min)) - 1),
      cv::Point(static_cast<int>(std::ceil(u_max)) + 2, static_cast<int>(std::ceil(v_max)) + 2));
  return rect & bounds;
}

// The rays of one view: through pixel (u, v), with camera-frame z = 1 so that a hit's t is its
// depth exactly, tested only against the boxes whose image rectangle holds the pixel.
class ViewRays {
 public:
  // A box as this view sees it: what cast() reads of it, together.
  struct Candidate {
    // From the camera to the box (0 inside it), a millionth kept in hand for rounding, squared:
    // cast() compares it without a root.
    double bound2;
    int index;           // in the scene
    int u_begin, u_end;  // the columns of its image rectangle
    // box.min - origin and box.max - origin: Scene::entryDistance's slab offsets, once a view;
    // and in floats, for the first pass's four lanes.
    Vec3 lo, hi;
    std::array<float, 3> lo_f, hi_f, min_f, max_f;  // min_f, max_f: box.min, box.max
    float albedo;
  };

  ViewRays(const Scene& scene, const camera::StereoCamera& camera, const Rigid3& T_map_camera,
           double max_depth, const cv::Rect& bounds)
      : camera_(camera),
        R_(T_map_camera.rotation.toRotationMatrix()),
        origin_(T_map_camera.translation),
        max_depth_(max_depth) {
    const Rigid3 T_camera_map = T_map_camera.inverse();
    for (size_t i = 0; i < scene.boxes().size(); ++i) {
      const SceneBox& box = scene.boxes()[i];
      const cv::Rect rect = projectedRect(box, T_camera_map, camera, bounds);
      const double distance = (box.min - origin_).cwiseMax(origin_ - box.max).cwiseMax(0.0).norm();
      candidates_.push_back({.bound2 = std::pow(distance * (1.0 - 1e-6), 2),
                             .index = static_cast<int>(i),
                             .u_begin = rect.x,
                             .u_end = rect.x + rect.width,
                             .lo = box.min - origin_,
                             .hi = box.max - origin_,
                             .lo_f = toFloats(box.min - origin_),
                             .hi_f = toFloats(box.max - origin_),
                             .min_f = toFloats(box.min),
                             .max_f = toFloats(box.max),
                             .albedo = box.albedo});
      rows_.emplace_back(rect.y, rect.y + rect.height);
    }
  }

  // The boxes that pixel row `v` can see, nearest to the camera first (cast() stops at the
  // first that cannot be nearer than its best hit).
  void boxesInRow(int v, std::vector<Candidate>& boxes) const {
    boxes.clear();
    for (size_t i = 0; i < candidates_.size(); ++i) {
      if (v >= rows_[i].first && v < rows_[i].second) boxes.push_back(candidates_[i]);
    }
    std::sort(boxes.begin(), boxes.end(),
              [](const Candidate& a, const Candidate& b) { return a.bound2 < b.bound2; });
  }
  Vec3 direction(double u, double v) const { return R_ * camera_.rayThrough(u, v); }

  struct Hit {
    double t;  // the depth
    const Candidate* box;
  };
  // Nearest hit within the maximum depth of a ray through pixel column `u` (a point within
  // half a pixel of its centre: the rectangles have a pixel's margin), among `boxes`; the ray
  // given by its direction and that direction's component-wise inverse.
  // The hit is the one testing every box in index order would give: the nearest, and of boxes
  // entered at the same t the last.
  std::optional<Hit> cast(int u, const Vec3& direction, const Vec3& inverse,
                          const std::vector<Candidate>& boxes) const {
    // A box entered at t lies at least its distance from the camera away, and the ray moves
    // |direction| per unit of t: t >= distance / |direction|, so boxes (nearest first) from
    // one whose bound passes the best hit on are all farther. Compared squared, as
    // distance^2 > t^2 |direction|^2: a root and a division a ray were the room's slowest
    // instructions (perf).
    const double length2 = direction.squaredNorm();
    const Candidate* best = nullptr;
    double best_t = max_depth_;
    double reach2 = best_t * best_t * length2;  // no box whose bound2 passes it is nearer
    for (const Candidate& box : boxes) {
      if (box.bound2 > reach2) break;
      if (u < box.u_begin || u >= box.u_end) continue;
      // Scene::entryDistance, its offsets from the camera taken once a view.
      const Vec3 t0 = box.lo.cwiseProduct(inverse);
      const Vec3 t1 = box.hi.cwiseProduct(inverse);
      const double t = t0.cwiseMin(t1).maxCoeff();
      if (t > 0 && t <= t0.cwiseMax(t1).minCoeff() &&
          (t < best_t || (t == best_t && (best == nullptr || box.index > best->index)))) {
        best_t = t;
        best = &box;
        reach2 = best_t * best_t * length2;
      }
    }
    if (best == nullptr) return std::nullopt;
    return Hit{best_t, best};
  }
  const Vec3& origin() const { return origin_; }
  const Eigen::Matrix3d& rotation() const { return R_; }
  double maxDepth() const { return max_depth_; }
  static std::array<float, 3> toFloats(const Vec3& v) {
    return {static_cast<float>(v.x()), static_cast<float>(v.y()), static_cast<float>(v.z())};
  }

 private:
  const camera::StereoCamera& camera_;
  const Eigen::Matrix3d R_;
  const Vec3 origin_;
  const double max_depth_;
  std::vector<Candidate> candidates_;      // in the scene's order
  std::vector<std::pair<int, int>> rows_;  // each box's image rows, [first, second)
};

// Sky: a flat grey with no texture, so stereo finds nothing there (as outdoors).
constexpr uint8_t kSkyGrey = 200;

// The anti-aliased view (supersample s > 1): one ray per pixel, the texture band-limited to the
// pixel's footprint, and s x s rays only in the pixels where the box hit or the paint changes.
// Brute force (s x s rays in every pixel) gave the same edges at about s^2 times the cost, and
// aliased the texture's 6 cm octave into noise at 30 m, where it fades here instead.
class AntiAliasedView {
 public:
  AntiAliasedView(const Scene& scene, const camera::StereoCamera& camera,
                  const Rigid3& T_map_camera, const RenderOptions& options)
      : scene_(scene),
        camera_(camera),
        s_(options.supersample),
        lanes_(options.lanes),
        // A ring of one pixel around the image is sampled too: an edge just outside a border
        // pixel's centre shows there.
        rays_(scene, camera, T_map_camera, options.max_depth,
              cv::Rect(-1, -1, camera.width + 2, camera.height + 2)),
        T_camera_map_(T_map_camera.inverse()),
        ray_per_u_(rays_.rotation().col(0) / camera.fx),
        ray_per_v_(rays_.rotation().col(1) / camera.fy),
        origin_f_(ViewRays::toFloats(rays_.origin())),
        ray_per_u_f_(ViewRays::toFloats(ray_per_u_)),
        ray_per_v_f_(ViewRays::toFloats(ray_per_v_)) {}

  // The image and, if `depth` is given, the depth at the pixel centres.
  void render(cv::Mat& image, cv::Mat* depth) const {
    const int width = camera_.width, height = camera_.height, stride = width + 2;
    image.create(height, width, CV_8UC1);
    if (depth != nullptr) depth->create(height, width, CV_32FC1);
    // First pass: the pixel centres, ring included (row/column k of the grid is pixel k - 1).
    const size_t grid = static_cast<size_t>(stride) * (height + 2);  // every one written
    const auto grey = std::make_unique_for_overwrite<float[]>(grid);
    const auto key = std::make_unique_for_overwrite<uint64_t[]>(grid);
    cv::parallel_for_(cv::Range(-1, height + 1), [&](const cv::Range& rows) {
      std::vector<ViewRays::Candidate> boxes;
      SurfaceShader shader(scene_);
      for (int v = rows.start; v < rows.end; ++v) {
        rays_.boxesInRow(v, boxes);
        const Vec3 row_direction = rays_.direction(0, v);
        const size_t row = static_cast<size_t>(v + 1) * stride + 1;
        float* depth_row =
            depth != nullptr && v >= 0 && v < height ? depth->ptr<float>(v) : nullptr;
        if (lanes_) {
          firstPassRow(row_direction, boxes, shader, &grey[row - 1], &key[row - 1], depth_row);
          continue;
        }
        for (int u = -1; u <= width; ++u) {
          const Sample sample = trace(row_direction + u * ray_per_u_, u, boxes, shader);
          grey[row + u] = sample.grey;
          key[row + u] = sample.key;
          if (depth_row != nullptr && u >= 0 && u < width) depth_row[u] = sample.depth;
        }
      }
    });
    // Second pass: a pixel whose centre differs in box or paint from any of its 8 neighbours'
    // has an edge within it (for a straight edge, always), as has one beside a corner. A box or
    // a stripe of paint narrower than a pixel can fall between the centres and be missed.
    // A 3 x 3 block differs from its centre where any two neighbours in it differ: each centre
    // compared with its right and lower neighbours once, in bytes that a row ORs together.
    cv::Mat edges = cornerPixels();
    const auto across = std::make_unique_for_overwrite<uint8_t[]>(grid);  // either side of it
    const auto down = std::make_unique_for_overwrite<uint8_t[]>(grid);    // it or a side, below
    cv::parallel_for_(cv::Range(0, height + 2), [&](const cv::Range& rows) {
      std::vector<uint8_t> right(stride);
      for (int g = rows.start; g < rows.end; ++g) {
        const uint64_t* k = &key[static_cast<size_t>(g) * stride];
        for (int c = 0; c + 1 < stride; ++c) right[c] = k[c] != k[c + 1];
        uint8_t* a = &across[static_cast<size_t>(g) * stride];
        uint8_t* d = &down[static_cast<size_t>(g) * stride];
        for (int c = 1; c + 1 < stride; ++c) a[c] = right[c - 1] | right[c];
        if (g == height + 1) continue;
        for (int c = 0; c < stride; ++c) right[c] = k[c] != k[c + stride];
        for (int c = 1; c + 1 < stride; ++c) d[c] = right[c - 1] | right[c] | right[c + 1];
      }
    });
    for (int v = 0; v < height; ++v) {
      uint8_t* e = edges.ptr<uint8_t>(v);
      const size_t row = static_cast<size_t>(v + 1) * stride + 1;  // pixel 0's centre
      for (int u = 0; u < width; ++u) {
        const size_t i = row + u;
        e[u] |= across[i - stride] | across[i] | across[i + stride] | down[i - stride] | down[i];
      }
    }
    cv::parallel_for_(cv::Range(0, height), [&](const cv::Range& rows) {
      std::vector<ViewRays::Candidate> boxes;
      SurfaceShader shader(scene_);
      for (int v = rows.start; v < rows.end; ++v) {
        rays_.boxesInRow(v, boxes);
        uint8_t* image_row = image.ptr<uint8_t>(v);
        const uint8_t* edge_row = edges.ptr<uint8_t>(v);
        const float* grey_row = &grey[static_cast<size_t>(v + 1) * stride + 1];
        for (int u = 0; u < width; ++u) {
          const float value = edge_row[u] != 0 ? supersampled(u, v, boxes, shader) : grey_row[u];
          image_row[u] = static_cast<uint8_t>(value + 0.5f);
        }
      }
    });
  }

 private:
  struct Sample {
    float grey = kSkyGrey;
    uint64_t key = 0;  // box and paint (0: sky); a change in it is an edge
    float depth = 0;
  };

  // The first pass's row whose ray at column 0 goes along `row_direction`: columns -1 to width,
  // `grey` and `key` from column -1, `depth` (if given) from column 0. Four neighbouring
  // columns at a time in floats, as trace() gives each in doubles: the same box and face
  // (but within a float's rounding of an edge, which the second pass then supersamples), the
  // same key, the grey within a float's rounding (callgrind: trace() took about 700
  // instructions a ray).
  STEREOMAP_LANES_CLONES void firstPassRow(const Vec3& row_direction,
                                           const std::vector<ViewRays::Candidate>& boxes,
                                           SurfaceShader& shader, float* grey, uint64_t* key,
                                           float* depth) const {
    using namespace detail;
    const int width = camera_.width;
    const std::array<float, 3> r = ViewRays::toFloats(row_direction);
    const std::array<float, 3>& du = ray_per_u_f_;
    for (int u0 = -1; u0 <= width; u0 += 4) {
      const F4 u = toFloat(splat(u0) + I4{0, 1, 2, 3});
      const Lanes lanes = trace4(r[0] + u * du[0], r[1] + u * du[1], r[2] + u * du[2], u, u0,
                                 u0 + 3, boxes, shader);
      if (u0 + 3 <= width) {
        std::memcpy(&grey[u0 + 1], &lanes.grey, sizeof(lanes.grey));
      } else {
        for (int l = 0; u0 + l <= width; ++l) grey[u0 + l + 1] = lanes.grey[l];
      }
      for (int l = 0; l < 4 && u0 + l <= width; ++l) {
        key[u0 + l + 1] = lanes.box[l] >= 0 ? (static_cast<uint64_t>(lanes.box[l] + 1) << 32) |
                                                  std::bit_cast<uint32_t>(lanes.albedo[l])
                                            : 0;
      }
      if (depth != nullptr) {
        if (u0 >= 0 && u0 + 3 < width) {
          std::memcpy(&depth[u0], &lanes.depth, sizeof(lanes.depth));
        } else {
          for (int l = 0; l < 4; ++l) {
            if (u0 + l >= 0 && u0 + l < width) depth[u0 + l] = lanes.depth[l];
          }
        }
      }
    }
  }

  // Four rays (lanes), each through a point of its pixel column `u`, along (dx, dy, dz): as
  // trace() on each, in floats (within a float's rounding of it).
  struct Lanes {
    detail::F4 grey, albedo, depth;  // depth 0 and grey the sky's where nothing is hit
    detail::I4 box;                  // -1: nothing hit
  };
  [[gnu::always_inline]] Lanes trace4(detail::F4 dx, detail::F4 dy, detail::F4 dz, detail::F4 u,
                                      int u_first, int u_last,
                                      const std::vector<ViewRays::Candidate>& boxes,
                                      SurfaceShader& shader) const {
    using namespace detail;
    const std::array<float, 3>&o = origin_f_, &du = ray_per_u_f_, &dv = ray_per_v_f_;
    const F4 ix = 1.0f / dx, iy = 1.0f / dy, iz = 1.0f / dz;
    const F4 length2 = dx * dx + dy * dy + dz * dz;
    F4 best_t = splat(static_cast<float>(rays_.maxDepth()));
    I4 best = splat(-1), axis = splat(0);
    F4 face = splat(0.0f), albedo = splat(0.0f);    // the hit face's coordinate, its albedo
    for (const ViewRays::Candidate& box : boxes) {  // as ViewRays::cast, in lanes
      const F4 reach2 = best_t * best_t * length2;
      if (box.bound2 > std::max(std::max(reach2[0], reach2[1]), std::max(reach2[2], reach2[3])))
        break;
      if (box.u_end <= u_first || box.u_begin > u_last) continue;
      const F4 ax = box.lo_f[0] * ix, bx = box.hi_f[0] * ix;
      const F4 ay = box.lo_f[1] * iy, by = box.hi_f[1] * iy;
      const F4 az = box.lo_f[2] * iz, bz = box.hi_f[2] * iz;
      const F4 nx = detail::min(ax, bx), ny = detail::min(ay, by), nz = detail::min(az, bz);
      const F4 t = detail::max(detail::max(nx, ny), nz);
      const F4 t_far =
          detail::min(detail::min(detail::max(ax, bx), detail::max(ay, by)), detail::max(az, bz));
      const I4 index = splat(box.index);
      const I4 better = (u >= static_cast<float>(box.u_begin)) &
                        (u < static_cast<float>(box.u_end)) & (t > 0.0f) & (t <= t_far) &
                        ((t < best_t) | ((t == best_t) & (index > best)));
      if (!any(better)) continue;
      best_t = select(better, t, best_t);
      best = select(better, index, best);
      // The face entered last, and its coordinate (the box's near side along that axis).
      const I4 along_x = (nx >= ny) & (nx >= nz), along_y = ~along_x & (ny >= nz);
      axis = select(better, select(along_x, splat(0), select(along_y, splat(1), splat(2))), axis);
      const F4 face_x = select(dx > 0.0f, splat(box.min_f[0]), splat(box.max_f[0]));
      const F4 face_y = select(dy > 0.0f, splat(box.min_f[1]), splat(box.max_f[1]));
      const F4 face_z = select(dz > 0.0f, splat(box.min_f[2]), splat(box.max_f[2]));
      face = select(better, select(along_x, face_x, select(along_y, face_y, face_z)), face);
      albedo = select(better, splat(box.albedo), albedo);
    }
    // The hits put on their faces exactly, as trace() does.
    const I4 hit = best >= 0;
    const F4 px = select(axis == 0, face, o[0] + best_t * dx);
    const F4 py = select(axis == 1, face, o[1] + best_t * dy);
    const F4 pz = select(axis == 2, face, o[2] + best_t * dz);
    const I4 top = hit & (axis == 2) & (dz < 0.0f);
    // The footprint, as trace(): step - (step[axis] / direction[axis]) direction per pixel.
    const F4 inverse_along = select(axis == 0, ix, select(axis == 1, iy, iz));
    auto along2 = [&](const std::array<float, 3>& step) {
      const F4 s =
          select(axis == 0, splat(step[0]), select(axis == 1, splat(step[1]), splat(step[2]))) *
          inverse_along;
      const F4 x = step[0] - s * dx, y = step[1] - s * dy, z = step[2] - s * dz;
      return x * x + y * y + z * z;
    };
    const F4 footprint = best_t * detail::sqrt(detail::max(along2(du), along2(dv)));
    Lanes lanes{.grey = splat(static_cast<float>(kSkyGrey)),
                .albedo = albedo,
                .depth = select(hit, best_t, splat(0.0f)),
                .box = best};
    if (any(hit)) shader.shade4(px, py, pz, best, top, footprint, lanes.grey, lanes.albedo);
    return lanes;
  }

  // The ray of pixel column `pixel_u` going along `direction`.
  Sample trace(const Vec3& direction, int pixel_u, const std::vector<ViewRays::Candidate>& boxes,
               SurfaceShader& shader) const {
    const Vec3 inverse = direction.cwiseInverse();
    const auto hit = rays_.cast(pixel_u, direction, inverse, boxes);
    if (!hit) return {};
    // The face it enters by (the slab entered last), and the hit put on it exactly: a deck's
    // top then lies on the texture's lattice plane, which halves the texture's cost.
    const ViewRays::Candidate& box = *hit->box;
    const Vec3 entry = box.lo.cwiseProduct(inverse).cwiseMin(box.hi.cwiseProduct(inverse));
    const int axis = entry.x() >= entry.y() ? (entry.x() >= entry.z() ? 0 : 2)
                                            : (entry.y() >= entry.z() ? 1 : 2);
    Vec3 p = rays_.origin() + hit->t * direction;
    const SceneBox& surface = scene_.boxes()[box.index];
    p[axis] = direction[axis] > 0 ? surface.min[axis] : surface.max[axis];
    // The pixel's footprint on the face (ray differentials): how far the hit moves on the face
    // per pixel along u and along v; the larger is what the texture must not be finer than.
    const Vec3 along_u = ray_per_u_ - (ray_per_u_[axis] * inverse[axis]) * direction;
    const Vec3 along_v = ray_per_v_ - (ray_per_v_[axis] * inverse[axis]) * direction;
    const double footprint =
        hit->t * std::sqrt(std::max(along_u.squaredNorm(), along_v.squaredNorm()));
    const SurfaceShader::Shade shade = shader.shade(p, box.index, footprint);
    return {
        .grey = shade.grey,
        .key = (static_cast<uint64_t>(box.index + 1) << 32) | std::bit_cast<uint32_t>(shade.albedo),
        .depth = static_cast<float>(hit->t)};
  }

  // The mean of s x s rays spread over pixel (u, v) as the pixel centres of an image s times
  // larger; the texture stays band-limited to this pixel's footprint, not the finer one's.
  float supersampled(int u, int v, const std::vector<ViewRays::Candidate>& boxes,
                     SurfaceShader& shader) const {
    const int n = s_ * s_;
    auto direction = [&](int k) {  // ray k of n, row by row
      return rays_.direction(u + (k % s_ + 0.5) / s_ - 0.5, v + (k / s_ + 0.5) / s_ - 0.5);
    };
    float sum = 0;
    if (!lanes_) {
      for (int k = 0; k < n; ++k) sum += trace(direction(k), u, boxes, shader).grey;
      return sum / static_cast<float>(n);
    }
    // Four rays at a time (the last four padded with copies of its first), summed in order.
    using namespace detail;
    for (int first = 0; first < n; first += 4) {
      alignas(16) std::array<std::array<float, 4>, 3> d;
      for (int l = 0; l < 4; ++l) {
        const auto ray = ViewRays::toFloats(direction(first + l < n ? first + l : first));
        for (int c = 0; c < 3; ++c) d[c][l] = ray[c];
      }
      F4 dx, dy, dz;
      std::memcpy(&dx, d[0].data(), sizeof(dx));
      std::memcpy(&dy, d[1].data(), sizeof(dy));
      std::memcpy(&dz, d[2].data(), sizeof(dz));
      const Lanes lanes = trace4(dx, dy, dz, splat(static_cast<float>(u)), u, u, boxes, shader);
      for (int l = 0; l < 4 && first + l < n; ++l) sum += lanes.grey[l];
    }
    return sum / static_cast<float>(n);
  }

  // Non-zero at and around (3 x 3) the pixels holding a box's corner or a marking's vertex: a
  // sharp corner can poke into a pixel between the centres that the first pass sampled.
  cv::Mat cornerPixels() const {
    cv::Mat corners = cv::Mat::zeros(camera_.height, camera_.width, CV_8UC1);
    auto mark = [&](const Vec3& p_map) {
      const Vec3 p = T_camera_map_ * p_map;
      if (p.z() < 1e-3) return;
      const auto uv = camera_.project(p);
      const cv::Point pixel(static_cast<int>(std::lround(uv->x())),
                            static_cast<int>(std::lround(uv->y())));
      const cv::Rect around =
          cv::Rect(pixel.x - 1, pixel.y - 1, 3, 3) & cv::Rect(0, 0, camera_.width, camera_.height);
      if (!around.empty()) corners(around).setTo(1);
    };
    for (const SceneBox& box : scene_.boxes()) {
      for (int corner = 0; corner < 8; ++corner) mark(box.corner(corner));
    }
    for (const SceneMarking& marking : scene_.markings()) {
      const double z = scene_.boxes()[marking.box].max.z();
      for (const auto& vertex : marking.polygon) mark(Vec3(vertex.x(), vertex.y(), z));
    }
    return corners;
  }

  const Scene& scene_;
  const camera::StereoCamera& camera_;
  const int s_;
  const bool lanes_;
  const ViewRays rays_;
  const Rigid3 T_camera_map_;
  const Vec3 ray_per_u_, ray_per_v_;  // the ray's change per pixel (map frame)
  const std::array<float, 3> origin_f_, ray_per_u_f_, ray_per_v_f_;  // the same in floats
};

}  // namespace

void Renderer::renderView(const Rigid3& T_map_camera, cv::Mat* image, cv::Mat* depth) const {
  if (image != nullptr && options_.supersample > 1) {
    AntiAliasedView(scene_, camera_, T_map_camera, options_).render(*image, depth);
    return;
  }
  // One ray per pixel centre, the texture exact: the rooms' images (tests' thresholds rest on
  // them, to the bit) and depth alone.
  if (image != nullptr) image->create(camera_.height, camera_.width, CV_8UC1);
  if (depth != nullptr) depth->create(camera_.height, camera_.width, CV_32FC1);
  const ViewRays rays(scene_, camera_, T_map_camera, options_.max_depth,
                      cv::Rect(0, 0, camera_.width, camera_.height));
  cv::parallel_for_(cv::Range(0, camera_.height), [&](const cv::Range& rows) {
    std::vector<ViewRays::Candidate> boxes;
    SurfaceShader shader(scene_);
    for (int v = rows.start; v < rows.end; ++v) {
      rays.boxesInRow(v, boxes);
      uint8_t* image_row = image != nullptr ? image->ptr<uint8_t>(v) : nullptr;
      float* depth_row = depth != nullptr ? depth->ptr<float>(v) : nullptr;
      for (int u = 0; u < camera_.width; ++u) {
        const Vec3 direction = rays.direction(u, v);
        const auto hit = rays.cast(u, direction, direction.cwiseInverse(), boxes);
        if (depth_row != nullptr) depth_row[u] = hit ? static_cast<float>(hit->t) : 0.0f;
        if (image_row != nullptr) {
          image_row[u] =
              hit ? static_cast<uint8_t>(
                        shader.shade(rays.origin() + hit->t * direction, hit->box->index).grey)
                  : kSkyGrey;
        }
      }
    }
  });
}

CameraModel CameraModel::typical() {
  return {.noise_sigma = 1.5,
          .shot_noise = 0.014,
          .blur_sigma = 0.5,
          .exposure_s = 0.004,
          .vignetting = 0.15,
          .right_gain = 1.05,
          .gamma = 1.1};
}

CameraModel CameraModel::poor() {
  return {.noise_sigma = 3.0,
          .shot_noise = 0.055,
          .blur_sigma = 1.0,
          .exposure_s = 0.010,
          .vignetting = 0.30,
          .right_gain = 1.10,
          .gamma = 1.25};
}

std::optional<CameraModel> CameraModel::preset(const std::string& name) {
  if (name == "clean") return clean();
  if (name == "typical") return typical();
  if (name == "poor") return poor();
  return std::nullopt;
}

namespace {

// A line kernel from -motion/2 to +motion/2 (pixels), summing to 1; empty when shorter than a
// tenth of a pixel.
cv::Mat motionKernel(const Eigen::Vector2d& motion) {
  const double length = motion.norm();
  if (!(length >= 0.1)) return {};
  const int half = static_cast<int>(std::ceil(0.5 * length)) + 1;
  cv::Mat kernel = cv::Mat::zeros(2 * half + 1, 2 * half + 1, CV_32F);
  // Sampled finely along the segment with bilinear weights, so that a sub-pixel length blurs
  // by that much.
  const int samples = std::max(8, static_cast<int>(std::ceil(8 * length)));
  for (int i = 0; i < samples; ++i) {
    const Eigen::Vector2d p = motion * ((i + 0.5) / samples - 0.5);
    const double x = p.x() + half, y = p.y() + half;
    const int x0 = static_cast<int>(std::floor(x)), y0 = static_cast<int>(std::floor(y));
    const double fx = x - x0, fy = y - y0;
    kernel.at<float>(y0, x0) += static_cast<float>((1 - fx) * (1 - fy));
    kernel.at<float>(y0, x0 + 1) += static_cast<float>(fx * (1 - fy));
    kernel.at<float>(y0 + 1, x0) += static_cast<float>((1 - fx) * fy);
    kernel.at<float>(y0 + 1, x0 + 1) += static_cast<float>(fx * fy);
  }
  return kernel / cv::sum(kernel)[0];
}

}  // namespace

void Renderer::finishImage(const Rigid3& T_map_camera, double gain, const cv::Mat& motion,
                           cv::Mat& image) const {
  const CameraModel& model = options_.camera;
  if (model.vignetting > 0 || gain != 1.0) {
    // Light falls off towards the corners (r^2 from the principal point, 1 at the farthest
    // corner); the camera's gain scales it all.
    cv::Mat light;
    image.convertTo(light, CV_32F);
    const double cx = camera_.cx, cy = camera_.cy;
    const double corner2 = std::max(cx * cx, (camera_.width - cx) * (camera_.width - cx)) +
                           std::max(cy * cy, (camera_.height - cy) * (camera_.height - cy));
    for (int v = 0; v < light.rows; ++v) {
      float* row = light.ptr<float>(v);
      for (int u = 0; u < light.cols; ++u) {
        const double r2 = ((u - cx) * (u - cx) + (v - cy) * (v - cy)) / corner2;
        row[u] = static_cast<float>(row[u] * gain * (1.0 - model.vignetting * r2));
      }
    }
    light.convertTo(image, CV_8U);
  }
  if (model.blur_sigma > 0) cv::GaussianBlur(image, image, cv::Size(), model.blur_sigma);
  if (!motion.empty())
    cv::filter2D(image, image, -1, motion, cv::Point(-1, -1), 0, cv::BORDER_REFLECT);
  if (model.noise_sigma > 0 || model.shot_noise > 0) {
    // A fresh pattern per image (one seed for all would be fixed-pattern noise that stereo
    // and tracking lock onto), reproducible from the seed and the pose.
    uint64_t seed = options_.noise_seed;
    for (const double v :
         {T_map_camera.translation.x(), T_map_camera.translation.y(), T_map_camera.translation.z(),
          T_map_camera.rotation.w(), T_map_camera.rotation.x(), T_map_camera.rotation.y()}) {
      seed = seed * 0x9E3779B97F4A7C15ull ^ std::hash<double>{}(v);
    }
    cv::RNG rng(seed);
    if (model.shot_noise > 0) {
      // sigma^2 = read^2 + shot * level, per pixel.
      cv::Mat level, unit(image.size(), CV_32F);
      image.convertTo(level, CV_32F);
      rng.fill(unit, cv::RNG::NORMAL, 0, 1);
      cv::Mat sigma;
      cv::sqrt(level * model.shot_noise + model.noise_sigma * model.noise_sigma, sigma);
      level += unit.mul(sigma);
      level.convertTo(image, CV_8U);
    } else {
      cv::Mat noise(image.size(), CV_16SC1);
      rng.fill(noise, cv::RNG::NORMAL, 0, model.noise_sigma);
      cv::Mat noisy;
      image.convertTo(noisy, CV_16SC1);
      noisy += noise;
      noisy.convertTo(image, CV_8UC1);
    }
  }
  if (model.gamma != 1.0) {
    cv::Mat table(1, 256, CV_8U);
    for (int i = 0; i < 256; ++i) {
      table.at<uint8_t>(i) =
          cv::saturate_cast<uint8_t>(255.0 * std::pow(i / 255.0, 1.0 / model.gamma));
    }
    cv::LUT(image, table, image);
  }
}

StereoFrame Renderer::render(const Rigid3& T_map_camera,
                             const std::optional<Exposure>& exposure) const {
  StereoFrame frame;
  frame.T_map_camera = T_map_camera;
  renderView(T_map_camera, &frame.left, &frame.depth);
  const Rigid3 T_left_right{common::Quat::Identity(), Vec3(camera_.baseline, 0, 0)};
  const Rigid3 T_map_right = T_map_camera * T_left_right;
  renderView(T_map_right, &frame.right, nullptr);
  cv::Mat motion;
  if (exposure && options_.camera.exposure_s > 0) {
    // The scene point seen at the image centre, at the median depth of the view, moves this
    // far in the image while the shutter is open (one kernel for the whole image: rotation
    // blurs alike everywhere; for translation it is right at the median depth).
    std::vector<float> depths;
    for (int v = 0; v < frame.depth.rows; ++v) {
      const float* row = frame.depth.ptr<float>(v);
      for (int u = 0; u < frame.depth.cols; ++u) {
        if (row[u] > 0) depths.push_back(row[u]);
      }
    }
    if (const auto median_depth = common::median(std::move(depths))) {
      const double z = *median_depth;
      const Vec3 p_map = T_map_camera * Vec3(0, 0, z);
      const auto open = camera_.project(exposure->T_map_camera_open.inverse() * p_map);
      const auto close = camera_.project(exposure->T_map_camera_close.inverse() * p_map);
      if (open && close) motion = motionKernel(*close - *open);
    }
  }
  finishImage(T_map_camera, 1.0, motion, frame.left);
  finishImage(T_map_right, options_.camera.right_gain, motion, frame.right);
  return frame;
}

cv::Mat Renderer::renderDepth(const Rigid3& T_map_camera) const {
  cv::Mat depth;
  renderView(T_map_camera, nullptr, &depth);
  return depth;
}

}  // namespace stereomap::sim
