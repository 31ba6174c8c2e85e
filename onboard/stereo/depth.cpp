#include "onboard/stereo/depth.hpp"

#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/ximgproc/disparity_filter.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <unordered_map>

namespace stereomap::stereo {

MatcherOptions MatcherOptions::fast() {
  MatcherOptions options;
  options.kind = MatcherKind::kBlockMatching;
  // 13 rather than 11: at 0.05 m voxels the far points' depth noise decides the map's
  // precision (0.949 against 0.959-0.969 on three sim rooms, docs/BENCHMARKS.md).
  options.block_size = 13;
  // The window's width: with DepthStep's start at the cloud's range (fitToRange), the sim
  // camera sees from 1.04 m to 6 m; 64 cost a third more time for nothing on the sim's maps
  // (docs/BENCHMARKS.md).
  options.num_disparities = 48;
  options.prefilter_cap = 31;  // BM's SIMD path needs <= 31: 63 doubles its time
  options.uniqueness_ratio = 15;
  options.speckle_window = 0;  // OpenCV's speckle filter costs 7.5 ms at 640x480, BM 10 ms
  options.left_right_max_diff = -1;
  // The left band holds far surfaces seen nowhere else in a turning flight (recall 0.83
  // without it at 0.05 m); its matches count only with the window inside the right image.
  options.pad_left = true;
  return options;
}

MatcherOptions MatcherOptions::accurate() {
  // Chosen on Middlebury against stock SGBM, and checked for sensitivity (every neighbouring
  // block size, penalty, cap, uniqueness and speckle value still beats stock; noise up to
  // sigma 5 keeps density >= 85%): see docs/BENCHMARKS.md.
  MatcherOptions options;
  options.kind = MatcherKind::kSemiGlobal;
  options.mode = SemiGlobalMode::kThreeWay;
  options.block_size = 5;
  options.p1 = 16;
  options.p2 = 32;
  options.prefilter_cap = 31;
  options.uniqueness_ratio = 10;
  options.left_right_max_diff = 1;
  options.speckle_window = 100;
  options.speckle_range = 2;
  return options;
}

int disparitiesFor(int max_disparity_px) { return std::max(16, (max_disparity_px + 15) / 16 * 16); }

int minimumDisparity(double baseline_m, double fx_px, double resolution_m, double dd_px) {
  return static_cast<int>(std::ceil(std::sqrt(baseline_m * fx_px * dd_px / resolution_m)));
}

MatcherOptions fitToRange(MatcherOptions options, const camera::StereoCamera& camera,
                          double max_range_m) {
  CV_Assert(max_range_m > 0);
  const int farthest = static_cast<int>(std::floor(camera.disparityFromDepth(max_range_m)));
  options.min_disparity = std::max(options.min_disparity, farthest);
  return options;
}

std::string searchProblem(const MatcherOptions& options, int image_width) {
  // OpenCV's disparities are int16 in 1/16 px, and its window must fit its image.
  constexpr int kMostDisparity = 2047;
  int largest = options.min_disparity + options.num_disparities;
  for (const auto& w : options.nearer) largest = std::max(largest, w.maxPx());
  if (options.min_disparity < image_width && largest <= kMostDisparity) return {};
  return "the disparity search (from " + std::to_string(options.min_disparity) + " to " +
         std::to_string(largest) + " px) lies beyond the image's " + std::to_string(image_width) +
         " px or OpenCV's " + std::to_string(kMostDisparity) +
         ": check the calibration's focal length and baseline, or --max-range";
}

RigRangeOptions rigRangeOptions(const MatcherOptions& matcher, double map_resolution_m,
                                double far_m) {
  return {.map_resolution_m = map_resolution_m,
          .precision_px = matcher.precision_px,
          .window_disparities = matcher.num_disparities,
          .far_m = far_m};
}

MatcherOptions fitToWindows(MatcherOptions options, const std::vector<DisparityWindow>& windows) {
  CV_Assert(!windows.empty() && windows.front().downscale == 1);
  options.min_disparity = windows.front().min_px;
  options.num_disparities = windows.front().num_px;
  options.downscale = 1;
  options.nearer.assign(windows.begin() + 1, windows.end());
  return options;
}

namespace {

int sgbmMode(SemiGlobalMode mode) {
  switch (mode) {
    case SemiGlobalMode::kFivePaths:
      return cv::StereoSGBM::MODE_SGBM;
    case SemiGlobalMode::kThreeWay:
      return cv::StereoSGBM::MODE_SGBM_3WAY;
    case SemiGlobalMode::kEightPaths:
      return cv::StereoSGBM::MODE_HH;
    case SemiGlobalMode::kEightPathsFourLines:
      return cv::StereoSGBM::MODE_HH4;
  }
  return cv::StereoSGBM::MODE_SGBM_3WAY;
}

// Laplacian of Gaussian, mapped to 8 bits around 128 (the paper's prefilter).
cv::Mat laplacianOfGaussian(const cv::Mat& image, double sigma) {
  cv::Mat blurred, laplacian, out;
  cv::GaussianBlur(image, blurred, cv::Size(), sigma);
  cv::Laplacian(blurred, laplacian, CV_16S, 3);
  laplacian.convertTo(out, CV_8U, -4.0, 128.0);
  return out;
}

// A window's match on its far edge (the surface lies farther), and a pixel two windows
// disagree on; both invalid (negative) in the disparity returned.
constexpr float kFarEdge = -3.0f;
constexpr float kConflict = -2.0f;
constexpr int kNearerUniqueness = 30;  // percent, see StereoMatcher's constructor
constexpr int kNearerSpeckle = 50;     // pixels of the reduced image, likewise
constexpr int kSmallestBlock = 5;      // OpenCV's BM takes no smaller block
// A semi-global match fills a nearer window's pixel (MatcherOptions::fill_nearer) when the
// images confirm it (confirmsMatch): its window, on the images as matched, fits the right
// image's within this share of the window's own texture, and holds at least this much texture
// (mean absolute deviation, grey levels). Measured on the reduced images: semi-global guesses
// on a textured wall beyond the window (stereo_test) fit at 0.5-1.9 of their texture, mostly
// 0.7-1.3, as unrelated patches do; Middlebury's candidates mostly at 0.2-0.6. Map recall on
// Middlebury 0.819 / 0.826 / 0.830 at 0.6 / 0.7 / 0.8, the wall's near pixels below 0.02 % at
// each; the texture floor (1 to 4: the same recall) keeps flat areas out, where any disparity
// fits.
constexpr float kFillFit = 0.7f;
constexpr float kFillTexture = 2.0f;
// The fill completes surfaces block matching found in its window: it runs only when they cover
// this share of the reduced image. In the sim's room, whose surfaces mostly lie beyond the
// nearer windows, block matching matched 0-3.6 % of the half-size window's image (median 0.3 %,
// 30 frames): the fill would cost 25 ms a frame there for a few pixels; aloe: 40 % at half
// size, 2.4 % at quarter size.
constexpr double kFillSurface = 0.02;
// Two windows that match a pixel differently: the match whose window of the images (zero-mean
// absolute differences) fits this much better than the other's is kept, otherwise neither.
// Measured on Middlebury: 0.6 to 1.0 give the same map (a repeated texture's wrong match fits
// far worse than the surface's).
constexpr float kArbitrationMargin = 0.8f;
constexpr int kGroundResidual = 8;  // px either side of the ground plane (matchGround)

// Whether the images confirm a match of the left image's pixel (u, v) at whole disparity d: the
// square window of `half` pixels around it fits the right image's (zero-mean absolute
// differences) within kFillFit of its own texture (mean absolute deviation), and holds at least
// kFillTexture of texture. False where a window leaves an image.
bool confirmsMatch(const cv::Mat& left, const cv::Mat& right, int u, int v, int d, int half) {
  if (v < half || v + half >= left.rows || u + half >= left.cols || u - d - half < 0) return false;
  const int n = (2 * half + 1) * (2 * half + 1);
  int sum_l = 0, sum_r = 0;
  for (int y = v - half; y <= v + half; ++y) {
    const uint8_t* l = left.ptr<uint8_t>(y) + u - half;
    const uint8_t* r = right.ptr<uint8_t>(y) + u - d - half;
    for (int x = 0; x <= 2 * half; ++x) {
      sum_l += l[x];
      sum_r += r[x];
    }
  }
  // In integers, scaled by n^2: the sums of |n l - n r - (S_l - S_r)| and of |n l - S_l|.
  int cost = 0, texture = 0;
  for (int y = v - half; y <= v + half; ++y) {
    const uint8_t* l = left.ptr<uint8_t>(y) + u - half;
    const uint8_t* r = right.ptr<uint8_t>(y) + u - d - half;
    for (int x = 0; x <= 2 * half; ++x) {
      cost += std::abs(n * (l[x] - r[x]) - (sum_l - sum_r));
      texture += std::abs(n * l[x] - sum_l);
    }
  }
  return texture >= kFillTexture * n * n && cost < kFillFit * texture;
}

// One window's matcher: OpenCV's, with what it needs between frames.
struct WindowMatcher {
  MatcherOptions options;      // this window's: its downscale, disparities and smoothing
  bool keep_far_edge = true;   // the first window's far edge is cut by the cloud's range
  bool keep_near_edge = true;  // the last window's near edge is the rig's nearest depth
  cv::Ptr<cv::StereoMatcher> matcher;
  cv::Ptr<cv::StereoMatcher> right_matcher;  // for the WLS filter
  cv::Ptr<cv::ximgproc::DisparityWLSFilter> wls;
  // Semi-global matching over the same window, for the pixels block matching leaves empty
  // (MatcherOptions::fill_nearer), and the window of the images its matches must fit.
  cv::Ptr<cv::StereoMatcher> fill;
  int fill_half = 0;
  // Reused between frames: a fresh 0.6 MB buffer costs page faults.
  cv::Mat fixed_point, fill_fixed_point;

  explicit WindowMatcher(const MatcherOptions& o) : options(o) {
    const int levels = o.num_disparities / o.downscale;
    const int num_disparities = disparitiesFor(levels);
    const int min_disparity = o.min_disparity / o.downscale;
    if (o.kind == MatcherKind::kBlockMatching) {
      auto bm = cv::StereoBM::create(num_disparities, o.block_size);
      bm->setMinDisparity(min_disparity);
      bm->setUniquenessRatio(o.uniqueness_ratio);
      bm->setTextureThreshold(o.texture_threshold);
      bm->setPreFilterCap(std::min(o.prefilter_cap, 63));
      bm->setDisp12MaxDiff(o.left_right_max_diff);
      matcher = bm;
    } else {
      const int area = o.block_size * o.block_size;
      matcher = cv::StereoSGBM::create(min_disparity, num_disparities, o.block_size, o.p1 * area,
                                       o.p2 * area, o.left_right_max_diff, o.prefilter_cap,
                                       o.uniqueness_ratio, 0, 0, sgbmMode(o.mode));
    }
    matcher->setSpeckleWindowSize(o.speckle_window);
    matcher->setSpeckleRange(o.speckle_range);
    if (o.wls_lambda > 0) {
      wls = cv::ximgproc::createDisparityWLSFilter(matcher);
      wls->setLambda(o.wls_lambda);
      wls->setSigmaColor(o.wls_sigma);
      right_matcher = cv::ximgproc::createRightMatcher(matcher);
    }
  }

  // Where block matching found nothing (its invalid value), the semi-global match, if it lies
  // inside the window (not on its edges) and the images confirm it (confirmsMatch). l and r:
  // the images as matched (reduced, padded).
  void fillFromSemiGlobal(const cv::Mat& l, const cv::Mat& r) {
    const int invalid = (matcher->getMinDisparity() - 1) * 16;
    // Beyond its far edge block matching's matches say nothing about this window.
    const int far_edge = matcher->getMinDisparity() * 16;
    if (cv::countNonZero(fixed_point > far_edge) <
        kFillSurface * static_cast<double>(fixed_point.total())) {
      return;
    }
    fill->compute(l, r, fill_fixed_point);
    const int inside_from = (matcher->getMinDisparity() + 1) * 16;
    const int inside_to = (matcher->getMinDisparity() + matcher->getNumDisparities() - 1) * 16;
    for (int v = 0; v < fixed_point.rows; ++v) {
      int16_t* out = fixed_point.ptr<int16_t>(v);
      const int16_t* in = fill_fixed_point.ptr<int16_t>(v);
      for (int u = 0; u < fixed_point.cols; ++u) {
        if (out[u] > invalid || in[u] < inside_from || in[u] >= inside_to) continue;
        // At the nearest whole disparity: the reduced image's pixel is coarse already.
        if (confirmsMatch(l, r, u, v, (in[u] + 8) >> 4, fill_half)) out[u] = in[u];
      }
    }
  }

  // Disparity of the full-size left image in pixels (CV_32FC1, < 0 invalid).
  cv::Mat compute(const cv::Mat& left, const cv::Mat& right) {
    const MatcherOptions& o = options;
    cv::Mat l = left, r = right;
    if (o.downscale > 1) {
      const cv::Size small((left.cols + o.downscale - 1) / o.downscale,
                           (left.rows + o.downscale - 1) / o.downscale);
      cv::resize(left, l, small, 0, 0, cv::INTER_AREA);
      cv::resize(right, r, small, 0, 0, cv::INTER_AREA);
    }
    const cv::Size matched = l.size();
    if (o.row_groups > 1) {
      const cv::Size grouped(l.cols, (l.rows + o.row_groups - 1) / o.row_groups);
      cv::resize(l, l, grouped, 0, 0, cv::INTER_AREA);
      cv::resize(r, r, grouped, 0, 0, cv::INTER_AREA);
    }
    if (o.smooth_sigma_px > 0) {
      cv::Mat smoothed_left, smoothed_right;
      // Grouped rows are smoothed along the rows only: the grouping has averaged them already,
      // and more vertical smoothing cost precision (typical camera 0.957 -> 0.943, measured).
      const cv::Size kernel =
          o.row_groups > 1 ? cv::Size(cvRound(o.smooth_sigma_px * 6 + 1) | 1, 1) : cv::Size();
      cv::GaussianBlur(l, smoothed_left, kernel, o.smooth_sigma_px);
      cv::GaussianBlur(r, smoothed_right, kernel, o.smooth_sigma_px);
      l = smoothed_left;
      r = smoothed_right;
    }
    if (o.prefilter == Prefilter::kLoG) {
      l = laplacianOfGaussian(l, o.log_sigma_px);
      r = laplacianOfGaussian(r, o.log_sigma_px);
    }
    // Without padding the matchers leave the first num_disparities columns empty; with it a
    // pixel there finds its match whenever the match is inside the right image.
    const int pad = o.pad_left ? matcher->getNumDisparities() + matcher->getMinDisparity() : 0;
    if (pad > 0) {
      cv::copyMakeBorder(l, l, 0, 0, pad, 0, cv::BORDER_REPLICATE);
      cv::copyMakeBorder(r, r, 0, 0, pad, 0, cv::BORDER_REPLICATE);
    }
    matcher->compute(l, r, fixed_point);  // CV_16S, 4 fractional bits
    if (fill) fillFromSemiGlobal(l, r);
    if (wls) {
      cv::Mat right_disparity, filtered;
      right_matcher->compute(r, l, right_disparity);
      // The filter's default region of interest leaves the left band empty: use all of it.
      wls->filter(fixed_point, l, filtered, right_disparity, cv::Rect(0, 0, l.cols, l.rows), r);
      fixed_point = filtered;
    }
    const int invalid_below = matcher->getMinDisparity() * 16;
    // Matches on an inner edge of the window: the true disparity may well lie beyond it. One
    // on the far edge says the surface lies farther than this window (kFarEdge).
    const int far_edge = keep_far_edge ? invalid_below : invalid_below + 16;
    const int last = (matcher->getMinDisparity() + matcher->getNumDisparities() - 1) * 16;
    const int near_edge = keep_near_edge ? last : last - 16;
    // With padding, a match counts only when the whole matching window lies inside the right
    // image (x - d >= half the block): windows reaching into the padding give biased matches.
    const int inside = o.block_size / 2;
    const float scale = static_cast<float>(o.downscale) / 16.0f;
    cv::Mat disparity(matched, CV_32FC1);
    for (int v = 0; v < disparity.rows; ++v) {
      const int16_t* in = fixed_point.ptr<int16_t>(v / o.row_groups) + pad;
      float* out = disparity.ptr<float>(v);
      for (int u = 0; u < disparity.cols; ++u) {
        const bool valid =
            in[u] >= far_edge && in[u] <= near_edge && (pad == 0 || in[u] <= (u - inside) * 16);
        out[u] = valid                                        ? in[u] * scale
                 : in[u] >= invalid_below && in[u] < far_edge ? kFarEdge
                                                              : -1.0f;
      }
    }
    if (o.downscale > 1) {
      cv::Mat full;
      cv::resize(disparity, full, left.size(), 0, 0, cv::INTER_NEAREST);  // keeps invalid apart
      disparity = full;
    }
    return disparity;
  }
};

// The ground as a plane whose disparity grows down the image, d = slope (v - horizon): a road
// ahead of a car, terrain ahead of a low drone. A matching block that spans block_size rows of it
// spans slope * block_size pixels of disparity, which block matching, made for surfaces facing
// the camera, does not find (KITTI: the road's 0.33 px a row is 4 px over 13 rows, 9 over the
// 26 of rows matched in pairs).
struct GroundPlane {
  double slope = 0, horizon = 0;
  double at(double v) const { return slope * (v - horizon); }
};

// The dominant plane of disparity rising down the image among `disparity`'s valid pixels
// (RANSAC over pairs of samples), when at least a tenth of them lie within half a pixel of it,
// and it rises by at least `min_slope` px a row; `previous` is tried as well.
std::optional<GroundPlane> fitGround(const cv::Mat& disparity, double min_slope,
                                     const std::optional<GroundPlane>& previous) {
  std::vector<cv::Point2f> samples;  // (v, d)
  for (int v = 0; v < disparity.rows; v += 2) {
    const float* row = disparity.ptr<float>(v);
    for (int u = 0; u < disparity.cols; u += 4) {
      if (row[u] > 0) samples.emplace_back(static_cast<float>(v), row[u]);
    }
  }
  if (samples.size() < 200) return std::nullopt;
  auto inliers = [&](const GroundPlane& g) {
    size_t n = 0;
    for (const auto& p : samples) n += std::abs(p.y - g.at(p.x)) <= 0.5;
    return n;
  };
  std::optional<GroundPlane> best;
  size_t best_count = 0;
  auto consider = [&](const GroundPlane& g) {
    if (!(g.slope >= min_slope)) return;
    const size_t n = inliers(g);
    if (n > best_count) best = g, best_count = n;
  };
  if (previous) consider(*previous);
  cv::RNG rng(0x5eed);  // the same samples give the same plane
  for (int i = 0; i < 64; ++i) {
    const auto& a = samples[rng.uniform(0, static_cast<int>(samples.size()))];
    const auto& b = samples[rng.uniform(0, static_cast<int>(samples.size()))];
    if (std::abs(a.x - b.x) < 8) continue;
    const double slope = (b.y - a.y) / (b.x - a.x);
    consider({slope, a.x - a.y / slope});
  }
  if (!best || best_count * 10 < samples.size()) return std::nullopt;
  // Least squares on its inliers.
  double sv = 0, sd = 0, svv = 0, svd = 0, n = 0;
  for (const auto& p : samples) {
    if (std::abs(p.y - best->at(p.x)) > 0.5) continue;
    sv += p.x, sd += p.y, svv += p.x * p.x, svd += p.x * p.y, ++n;
  }
  const double denominator = n * svv - sv * sv;
  if (denominator <= 0) return best;
  const double slope = (n * svd - sv * sd) / denominator;
  const double offset = (sd - slope * sv) / n;  // d = slope v + offset
  if (!(slope >= min_slope)) return best;
  return GroundPlane{slope, -offset / slope};
}

// Zero-mean SAD of the left image's window around (u, v) against the right image's around
// u - d (linear interpolation between columns), per pixel; infinity where the window leaves
// either image.
float windowCost(const cv::Mat& left, const cv::Mat& right, int u, int v, float d, int half_cols,
                 int half_rows) {
  const int k = static_cast<int>(std::floor(d));
  const float f = d - static_cast<float>(k);
  if (v - half_rows < 0 || v + half_rows >= left.rows || u + half_cols >= left.cols ||
      u - k - 1 - half_cols < 0) {
    return std::numeric_limits<float>::infinity();
  }
  // The right image between columns x - k and x - k - 1: the disparity's sub-pixel part.
  const auto rightAt = [&](const uint8_t* row, int x) {
    return (1 - f) * row[x - k] + f * row[x - k - 1];
  };
  const int n = (2 * half_cols + 1) * (2 * half_rows + 1);
  float sum_l = 0, sum_r = 0;
  for (int y = v - half_rows; y <= v + half_rows; ++y) {
    const uint8_t* l = left.ptr<uint8_t>(y);
    const uint8_t* r = right.ptr<uint8_t>(y);
    for (int x = u - half_cols; x <= u + half_cols; ++x) {
      sum_l += l[x];
      sum_r += rightAt(r, x);
    }
  }
  // Zero-mean: a gain or exposure offset between the cameras does not decide.
  const float offset = (sum_l - sum_r) / static_cast<float>(n);
  float cost = 0;
  for (int y = v - half_rows; y <= v + half_rows; ++y) {
    const uint8_t* l = left.ptr<uint8_t>(y);
    const uint8_t* r = right.ptr<uint8_t>(y);
    for (int x = u - half_cols; x <= u + half_cols; ++x) {
      cost += std::abs(l[x] - offset - rightAt(r, x));
    }
  }
  return cost / static_cast<float>(n);
}

}  // namespace

struct StereoMatcher::Impl {
  MatcherOptions options;
  std::vector<WindowMatcher> windows;  // the first at options' own window, then `nearer`
  // The ground pass (MatcherOptions::ground): a matcher of residual disparities around the
  // ground plane, and the plane found last.
  std::optional<WindowMatcher> ground;
  std::optional<GroundPlane> plane;
  // The right image moved row by row by the plane's disparity, and where from: reused between
  // frames (at KITTI's size 3.7 MB a frame otherwise).
  cv::Mat sheared, map_x, map_y;

  void matchGround(const cv::Mat& left, const cv::Mat& right, cv::Mat& disparity);
  // Of two windows' disparities a and b at (u, v): the one whose window of the full images fits
  // clearly better (kArbitrationMargin), or kConflict. The window is the first matcher's.
  float arbitrate(const cv::Mat& left, const cv::Mat& right, int u, int v, float a, float b) const {
    if (!options.arbitrate) return kConflict;
    const int half_cols = options.block_size / 2;
    const int half_rows = options.block_size * options.row_groups / 2;
    const float cost_a = windowCost(left, right, u, v, a, half_cols, half_rows);
    const float cost_b = windowCost(left, right, u, v, b, half_cols, half_rows);
    if (cost_a < kArbitrationMargin * cost_b) return a;
    if (cost_b < kArbitrationMargin * cost_a) return b;
    return kConflict;
  }
};

// Matches the rows below the horizon again on a right image sheared by the ground plane, so
// that the ground faces the matcher (its residual disparity is 0), and takes the ground's
// disparities where the windows found none. A pixel where both found one must agree.
void StereoMatcher::Impl::matchGround(const cv::Mat& left, const cv::Mat& right,
                                      cv::Mat& disparity) {
  const double window_rows = options.block_size * options.row_groups;
  // Below a pixel of disparity over a block's rows the windows find the ground themselves.
  plane = fitGround(disparity, 1.0 / window_rows, plane);
  if (!plane) return;
  const GroundPlane g = *plane;
  const int first_row = std::clamp(static_cast<int>(std::ceil(g.horizon)) + 1, 0, left.rows);
  if (left.rows - first_row < 2 * window_rows) return;
  // right'(x, v) = right(x - g(v), v): a left pixel on the ground matches right' at x - 0.
  map_x.create(left.rows - first_row, left.cols, CV_32FC1);
  map_y.create(map_x.size(), CV_32FC1);
  for (int r = 0; r < map_x.rows; ++r) {
    const float shift = static_cast<float>(g.at(first_row + r));
    float* mx = map_x.ptr<float>(r);
    float* my = map_y.ptr<float>(r);
    for (int u = 0; u < map_x.cols; ++u) {
      mx[u] = static_cast<float>(u) - shift;
      my[u] = static_cast<float>(first_row + r);
    }
  }
  cv::remap(right, sheared, map_x, map_y, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
  const cv::Mat residual = ground->compute(left.rowRange(first_row, left.rows), sheared);
  const float lowest = static_cast<float>(windows.front().options.min_disparity);
  const auto& last = windows.back().options;
  const float highest = static_cast<float>(last.min_disparity + last.num_disparities);
  for (int r = 0; r < residual.rows; ++r) {
    const int v = first_row + r;
    const float* in = residual.ptr<float>(r);
    float* out = disparity.ptr<float>(v);
    const float shift = static_cast<float>(g.at(v));
    for (int u = 0; u < residual.cols; ++u) {
      if (in[u] == -1.0f || in[u] == kFarEdge || in[u] == kConflict) continue;
      const float d = in[u] + shift;
      // Not matched beyond the image's left edge, and within the windows' range.
      if (d < lowest || d >= highest || d > u - options.block_size / 2) continue;
      if (out[u] == -1.0f) {
        out[u] = d;
      } else if (out[u] >= 0 && std::abs(out[u] - d) > 1.0f) {
        out[u] = kConflict;
      }
    }
  }
}

StereoMatcher::StereoMatcher(const MatcherOptions& options) : impl_(std::make_unique<Impl>()) {
  CV_Assert(options.num_disparities > 0 && options.num_disparities % 16 == 0);
  CV_Assert(options.block_size % 2 == 1 && options.downscale >= 1 && options.row_groups >= 1);
  impl_->options = options;
  impl_->windows.emplace_back(options);
  for (const DisparityWindow& w : options.nearer) {
    CV_Assert(w.downscale >= 1 && w.num_px > 0 && w.num_px % (16 * w.downscale) == 0 &&
              w.min_px % w.downscale == 0);
    MatcherOptions o = options;
    o.nearer.clear();
    o.downscale = w.downscale;
    o.min_disparity = w.min_px;
    o.num_disparities = w.num_px;
    // Reduced images have averaged their rows and smoothed already.
    o.row_groups = w.downscale > 1 ? 1 : options.row_groups;
    o.smooth_sigma_px = options.smooth_sigma_px / w.downscale;
    // Stricter on reduced images: a left-right check, a higher uniqueness and no speckles.
    // Foliage beyond the range repeats within their wide windows and gave near points in the
    // trees (KITTI); a near surface is large in the image, a false match small. Speckles cost
    // little on a reduced image (7.5 ms at 640x480, a quarter of it here).
    // The block covers what the first window's covers in the full image, not `downscale` times
    // as much: a reduced pixel already averages downscale² of them, and a wider block spans
    // thin near things and what lies behind them (Middlebury's aloe: 217 -> 220 of 303 voxels
    // at half size found, stereomap-bench-realrigs).
    if (w.downscale > 1) {
      o.left_right_max_diff = o.left_right_max_diff < 0 ? 1 : o.left_right_max_diff;
      o.uniqueness_ratio = std::max(o.uniqueness_ratio, kNearerUniqueness);
      o.speckle_window = std::max(o.speckle_window, kNearerSpeckle);
      o.speckle_range = std::max(o.speckle_range, 2);
      const double side = options.block_size * std::sqrt(options.row_groups) / w.downscale;
      o.block_size = std::max(kSmallestBlock, static_cast<int>(std::lround(side)) | 1);
    }
    impl_->windows.emplace_back(o);
    if (w.downscale > 1 && options.fill_nearer && o.kind == MatcherKind::kBlockMatching) {
      // The accurate preset's semi-global matching (penalties, three-way) at the smallest
      // block, as strict as the window's block matching; the fit's window is that block's.
      // Middlebury's map recall 0.775 -> 0.826 (aloe's leaves), sim maps unchanged
      // (map_accuracy_test); 4 ms more a clean 640x480 frame over a sim flight, about 25 ms
      // (one core) on frames where it runs (stereomap-bench-stereo, docs/BENCHMARKS.md).
      WindowMatcher& window = impl_->windows.back();
      const MatcherOptions semi_global = MatcherOptions::accurate();
      const int area = kSmallestBlock * kSmallestBlock;
      window.fill = cv::StereoSGBM::create(
          window.matcher->getMinDisparity(), window.matcher->getNumDisparities(), kSmallestBlock,
          semi_global.p1 * area, semi_global.p2 * area, o.left_right_max_diff,
          semi_global.prefilter_cap, o.uniqueness_ratio, o.speckle_window, o.speckle_range,
          sgbmMode(semi_global.mode));
      window.fill_half = o.block_size / 2;
    }
  }
  // With several windows every far edge tells the nearer windows off (compute()); the first
  // one's lies beyond the range anyway (fitToRange's rounding down).
  for (size_t i = 0; i + 1 < impl_->windows.size(); ++i) {
    impl_->windows[i].keep_near_edge = false;
    impl_->windows[i].keep_far_edge = false;
  }
  if (impl_->windows.size() > 1) impl_->windows.back().keep_far_edge = false;
  if (options.ground) {
    // Residual disparities around the plane: a surface within a few pixels of it.
    MatcherOptions o = options;
    o.nearer.clear();
    o.downscale = 1;
    o.min_disparity = -kGroundResidual;
    o.num_disparities = 2 * kGroundResidual;
    o.pad_left = false;
    impl_->ground.emplace(o);
    impl_->ground->keep_far_edge = impl_->ground->keep_near_edge = false;
  }
}

StereoMatcher::~StereoMatcher() = default;
StereoMatcher::StereoMatcher(StereoMatcher&&) noexcept = default;
StereoMatcher& StereoMatcher::operator=(StereoMatcher&&) noexcept = default;
const MatcherOptions& StereoMatcher::options() const { return impl_->options; }

cv::Mat StereoMatcher::compute(const cv::Mat& left, const cv::Mat& right) const {
  CV_Assert(left.type() == CV_8UC1 && right.type() == CV_8UC1 && left.size() == right.size());
  cv::Mat disparity = impl_->windows.front().compute(left, right);
  for (size_t i = 1; i < impl_->windows.size(); ++i) {
    const cv::Mat nearer = impl_->windows[i].compute(left, right);
    // Far to near. A pixel a farther window saw beyond its far edge lies farther still: what a
    // nearer window matches there is a repeated texture (foliage), not the surface. Two windows
    // that both matched must agree (within the coarser one's pixel, where they overlap);
    // otherwise the images decide (arbitrate), and neither is trusted when they cannot: on
    // aloe's repeated wallpaper 0.758 -> 0.810 of the pixels came out right (stereo_test).
    const float tolerance = static_cast<float>(impl_->windows[i].options.downscale);
    for (int v = 0; v < disparity.rows; ++v) {
      float* out = disparity.ptr<float>(v);
      const float* in = nearer.ptr<float>(v);
      for (int u = 0; u < disparity.cols; ++u) {
        if (out[u] == kFarEdge || out[u] == kConflict) continue;
        if (in[u] >= 0) {
          if (out[u] < 0) {
            out[u] = in[u];
          } else if (std::abs(out[u] - in[u]) > tolerance) {
            out[u] = impl_->arbitrate(left, right, u, v, out[u], in[u]);
          }
        } else if (in[u] == kFarEdge && out[u] < 0) {
          out[u] = kFarEdge;
        }
      }
    }
  }
  if (impl_->ground) impl_->matchGround(left, right, disparity);
  return disparity;
}

BlockDisparity blockDisparity(const cv::Mat& disparity, const cv::Mat& left,
                              const camera::StereoCamera& camera, const CloudOptions& options) {
  CV_Assert(disparity.type() == CV_32FC1);
  CV_Assert(!options.with_intensity || (left.type() == CV_8UC1 && left.size() == disparity.size()));
  CV_Assert(options.block_cols >= 1 && options.block_rows >= 1);
  const double min_disparity = camera.disparityFromDepth(options.max_range_m);
  const double max_disparity = camera.disparityFromDepth(options.min_range_m);
  const float offset = static_cast<float>(options.disparity_offset_px);
  const float bf = static_cast<float>(camera.baseline * camera.fx);
  const int block_pixels = options.block_cols * options.block_rows;
  const int grid_rows = disparity.rows / options.block_rows;
  const int grid_cols = disparity.cols / options.block_cols;

  // Each block's median disparity (x16, fixed point as OpenCV's speckle filter wants;
  // -16 = no point) and mean intensity.
  cv::Mat block_disparity(grid_rows, grid_cols, CV_16SC1, cv::Scalar(-16));
  BlockDisparity blocks{.disparity = cv::Mat(),
                        .intensity = cv::Mat(grid_rows, grid_cols, CV_8UC1, cv::Scalar(0)),
                        .block_cols = options.block_cols,
                        .block_rows = options.block_rows};
  cv::Mat& block_intensity = blocks.intensity;
  std::vector<float> valid(static_cast<size_t>(block_pixels));
  for (int by = 0; by < grid_rows; ++by) {
    const int v0 = by * options.block_rows;
    int16_t* out_disparity = block_disparity.ptr<int16_t>(by);
    uint8_t* out_intensity = block_intensity.ptr<uint8_t>(by);
    for (int bx = 0; bx < grid_cols; ++bx) {
      const int u0 = bx * options.block_cols;
      int count = 0, intensity_sum = 0;
      float sum = 0, lo = std::numeric_limits<float>::max(), hi = 0;
      for (int v = v0; v < v0 + options.block_rows; ++v) {
        const float* row = disparity.ptr<float>(v) + u0;
        const uint8_t* grey = options.with_intensity ? left.ptr<uint8_t>(v) + u0 : nullptr;
        for (int i = 0; i < options.block_cols; ++i) {
          const float d = row[i] + offset;
          if (row[i] > 0 && d >= min_disparity && d <= max_disparity) {
            valid[count++] = d;
            sum += d;
            lo = std::min(lo, d);
            hi = std::max(hi, d);
            if (grey != nullptr) intensity_sum += grey[i];
          }
        }
      }
      if (count == 0 || 2 * count < block_pixels) continue;
      if (hi - lo > options.max_block_span_px &&
          !(bf / lo - bf / hi <= options.max_block_depth_span_m)) {
        continue;
      }
      // One surface (values within 1 px): their mean; otherwise the median, so that a block
      // on a depth edge takes one side instead of a point in the air between them.
      float value = sum / static_cast<float>(count);
      if (hi - lo > 1.0f) {
        const auto middle = valid.begin() + count / 2;
        std::nth_element(valid.begin(), middle, valid.begin() + count);
        value = *middle;
      }
      out_disparity[bx] = static_cast<int16_t>(std::min(std::lround(value * 16.0f), 32767L));
      out_intensity[bx] = static_cast<uint8_t>(intensity_sum / count);
    }
  }
  // Speckles (small islands of disparity unlike their surroundings) are mostly mismatches;
  // filtering the block grid costs a tenth of filtering the full image.
  if (options.speckle_blocks > 0) {
    cv::filterSpeckles(block_disparity, -16, options.speckle_blocks,
                       static_cast<double>(options.speckle_range_px * 16));
  }
  block_disparity.convertTo(blocks.disparity, CV_32FC1, 1.0 / 16);
  return blocks;
}

common::PointCloud cloudFromBlocks(const BlockDisparity& blocks, const camera::StereoCamera& camera,
                                   const CloudOptions& options) {
  CV_Assert(blocks.disparity.type() == CV_32FC1 &&
            (!options.with_intensity || blocks.intensity.size() == blocks.disparity.size()));
  const int grid_rows = blocks.disparity.rows, grid_cols = blocks.disparity.cols;
  common::PointCloud cloud;
  cloud.points.reserve(static_cast<size_t>(grid_rows) * grid_cols);
  if (options.with_intensity) cloud.intensity.reserve(cloud.points.capacity());
  const double baseline_fx = camera.baseline * camera.fx;  // z = B f / d
  for (int by = 0; by < grid_rows; ++by) {
    const double v_centre = blocks.vCentre(by);
    const float* d = blocks.disparity.ptr<float>(by);
    const uint8_t* grey = blocks.intensity.ptr<uint8_t>(by);
    for (int bx = 0; bx < grid_cols; ++bx) {
      if (d[bx] <= 0) continue;
      const double depth = baseline_fx / d[bx];
      cloud.points.push_back(
          (camera.rayThrough(blocks.uCentre(bx), v_centre) * depth).cast<float>());
      if (options.with_intensity) cloud.intensity.push_back(grey[bx]);
    }
  }
  return options.voxel_m > 0 ? voxelGridDownsample(cloud, options.voxel_m) : cloud;
}

common::PointCloud cloudFromDisparity(const cv::Mat& disparity, const cv::Mat& left,
                                      const camera::StereoCamera& camera,
                                      const CloudOptions& options) {
  return cloudFromBlocks(blockDisparity(disparity, left, camera, options), camera, options);
}

float farthestPoint(const common::PointCloud& cloud, float at_least) {
  float longest = at_least;
  for (const auto& p : cloud.points) longest = std::max(longest, p.norm());
  return longest;
}

uint64_t gridKey(const common::Vec3& p, double voxel_m) {
  auto index = [voxel_m](double x) {
    return static_cast<uint64_t>(static_cast<int64_t>(std::floor(x / voxel_m)) + (1 << 20)) &
           0x1FFFFF;
  };
  return index(p.x()) | index(p.y()) << 21 | index(p.z()) << 42;
}

common::PointCloud voxelGridDownsample(const common::PointCloud& cloud, double voxel_m,
                                       const common::Rigid3& T_grid_cloud) {
  CV_Assert(voxel_m > 0);
  struct Cell {
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    uint32_t intensity_sum = 0;
    uint32_t count = 0;
  };
  const Eigen::Matrix3d R = T_grid_cloud.rotation.toRotationMatrix();
  const common::Vec3 t = T_grid_cloud.translation;
  auto key = [&](const common::Vec3f& p) { return gridKey(R * p.cast<double>() + t, voxel_m); };
  std::unordered_map<uint64_t, uint32_t> slot;
  std::vector<Cell> cells;
  slot.reserve(cloud.size());
  for (size_t i = 0; i < cloud.size(); ++i) {
    auto [it, inserted] =
        slot.try_emplace(key(cloud.points[i]), static_cast<uint32_t>(cells.size()));
    if (inserted) cells.emplace_back();
    Cell& cell = cells[it->second];
    cell.sum += cloud.points[i].cast<double>();
    if (cloud.hasIntensity()) cell.intensity_sum += cloud.intensity[i];
    ++cell.count;
  }
  common::PointCloud out;
  out.points.reserve(cells.size());
  for (const Cell& cell : cells) {
    out.points.push_back((cell.sum / cell.count).cast<float>());
    if (cloud.hasIntensity())
      out.intensity.push_back(static_cast<uint8_t>(cell.intensity_sum / cell.count));
  }
  return out;
}

}  // namespace stereomap::stereo
