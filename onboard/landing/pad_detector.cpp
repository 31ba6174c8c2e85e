#include "onboard/landing/pad_detector.hpp"

#include <algorithm>
#include <climits>
#include <cmath>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>

namespace stereomap::landing {

using common::Vec3;

const std::array<Vec3, 8>& padModel() {
  static const std::array<Vec3, 8> corners = {Vec3(0, 0, 0), Vec3(3, 0, 0), Vec3(3, 1, 0),
                                              Vec3(2, 1, 0), Vec3(2, 4, 0), Vec3(1, 4, 0),
                                              Vec3(1, 1, 0), Vec3(0, 1, 0)};
  return corners;
}

namespace {

double cross(const cv::Point2d& a, const cv::Point2d& b) { return a.x * b.y - a.y * b.x; }

// Twice the signed area; positive for a polygon clockwise in the image (y down).
double signedArea(const std::vector<cv::Point2d>& polygon) {
  double area = 0;
  for (size_t i = 0; i < polygon.size(); ++i) {
    area += cross(polygon[i], polygon[(i + 1) % polygon.size()]);
  }
  return area;
}

// The polygon of exactly 8 vertices that approximates a contour, trying tolerances from fine
// to coarse; empty when none gives 8.
std::vector<cv::Point2d> eightVertices(const std::vector<cv::Point>& contour) {
  const double perimeter = cv::arcLength(contour, true);
  for (double fraction = 0.005; fraction <= 0.06; fraction *= 1.25) {
    std::vector<cv::Point> polygon;
    cv::approxPolyDP(contour, polygon, fraction * perimeter, true);
    if (polygon.size() == 8) return {polygon.begin(), polygon.end()};
    if (polygon.size() < 8) break;
  }
  return {};
}

// Where two lines (point, direction) cross; nullopt when nearly parallel.
std::optional<cv::Point2d> crossing(const cv::Vec4f& a, const cv::Vec4f& b) {
  const cv::Point2d d1(a[0], a[1]), p1(a[2], a[3]), d2(b[0], b[1]), p2(b[2], b[3]);
  const double det = cross(d1, d2);
  if (std::abs(det) < 0.2) return std::nullopt;  // under about 12 degrees apart
  return p1 + d1 * (cross(p2 - p1, d2) / det);
}

// The line (direction, point) through points weighted by w: their weighted centroid and the
// principal direction of their weighted scatter.
cv::Vec4f weightedLine(const std::vector<cv::Point2f>& points, const std::vector<double>& w) {
  double sw = 0, sx = 0, sy = 0;
  for (size_t i = 0; i < points.size(); ++i) {
    sw += w[i];
    sx += w[i] * points[i].x;
    sy += w[i] * points[i].y;
  }
  const double cx = sx / sw, cy = sy / sw;
  double xx = 0, xy = 0, yy = 0;
  for (size_t i = 0; i < points.size(); ++i) {
    const double dx = points[i].x - cx, dy = points[i].y - cy;
    xx += w[i] * dx * dx;
    xy += w[i] * dx * dy;
    yy += w[i] * dy * dy;
  }
  const double angle = 0.5 * std::atan2(2 * xy, xx - yy);
  return {static_cast<float>(std::cos(angle)), static_cast<float>(std::sin(angle)),
          static_cast<float>(cx), static_cast<float>(cy)};
}

// A line robust to a few stray points: Huber's weights (1.345 px, as cv::fitLine's
// DIST_HUBER), reweighted from the least-squares line until it settles (0.01 px and 0.01 rad,
// as there). cv::fitLine does the same from 20 random starts and keeps the line of least
// summed distance; here the points lie along one edge, so one start from all of them does,
// at a twentieth of the cost (it was most of the watch's time on the final approach).
cv::Vec4f huberLine(const std::vector<cv::Point2f>& points) {
  constexpr double kHuber = 1.345;
  std::vector<double> w(points.size(), 1.0);
  cv::Vec4f line = weightedLine(points, w);
  for (int iteration = 0; iteration < 30; ++iteration) {
    for (size_t i = 0; i < points.size(); ++i) {
      const double r =
          std::abs(line[0] * (points[i].y - line[3]) - line[1] * (points[i].x - line[2]));
      w[i] = r < kHuber ? 1.0 : kHuber / r;
    }
    const cv::Vec4f next = weightedLine(points, w);
    const double turn = std::acos(
        std::min(1.0, std::abs(static_cast<double>(next[0] * line[0] + next[1] * line[1]))));
    const double shift = std::max(std::abs(next[2] - line[2]), std::abs(next[3] - line[3]));
    line = next;
    if (turn < 0.01 && shift < 0.01) break;
  }
  return line;
}

// A line through points, fitted again without those farther than 1.5 px from it (a dark
// speck of the deck merged into the T's outline bulges its edge).
cv::Vec4f trimmedLine(std::vector<cv::Point2f> points,
                      std::vector<cv::Point2f>* kept_out = nullptr) {
  cv::Vec4f line;
  for (int round = 0; round < 3; ++round) {
    line = huberLine(points);
    const cv::Point2f d(line[0], line[1]), p(line[2], line[3]);
    std::vector<cv::Point2f> kept;
    for (const auto& q : points) {
      if (std::abs(d.x * (q.y - p.y) - d.y * (q.x - p.x)) <= 1.5f) kept.push_back(q);
    }
    if (kept.size() < 2 || kept.size() == points.size()) break;
    points = std::move(kept);
  }
  if (kept_out != nullptr) *kept_out = std::move(points);
  return line;
}

// At most kMaxEdgePoints of `points`, evenly spread over them (they run along one edge): a fit's
// cost stays bounded however long the edge is in the image.
std::vector<cv::Point2f> evenlyThinned(std::vector<cv::Point2f> points) {
  if (points.size() <= static_cast<size_t>(kMaxEdgePoints)) return points;
  std::vector<cv::Point2f> kept(kMaxEdgePoints);
  const double step = static_cast<double>(points.size() - 1) / (kMaxEdgePoints - 1);
  for (int i = 0; i < kMaxEdgePoints; ++i) kept[i] = points[static_cast<size_t>(i * step + 0.5)];
  return kept;
}

// The polygon's vertices again, as the crossings of lines fitted to the contour's points
// along each side (approxPolyDP puts a vertex on a contour point, which a rounded or noisy
// corner pulls off): each point goes to its nearest side, away from the side's ends.
std::vector<cv::Point2d> fitSides(const std::vector<cv::Point>& contour,
                                  const std::vector<cv::Point2d>& polygon) {
  const size_t n = polygon.size();
  std::vector<std::vector<cv::Point2f>> sides(n);
  // Every contour point, or an even share of a long contour: a side keeps at most
  // kMaxEdgePoints (evenlyThinned) however many it was offered.
  const size_t stride = std::max<size_t>(1, contour.size() / (4 * n * kMaxEdgePoints));
  for (size_t index = 0; index < contour.size(); index += stride) {
    const cv::Point2d p(contour[index].x, contour[index].y);
    size_t best = 0;
    double best_distance = 1e18, best_s = 0, best_length = 0;
    for (size_t k = 0; k < n; ++k) {
      const cv::Point2d a = polygon[k], ab = polygon[(k + 1) % n] - a;
      const double length = cv::norm(ab);
      if (length < 1e-9) continue;
      const double s = std::clamp((p - a).dot(ab) / length, 0.0, length);
      const double distance = cv::norm(p - (a + ab * (s / length)));
      if (distance < best_distance) {
        best_distance = distance;
        best = k;
        best_s = s;
        best_length = length;
      }
    }
    const double margin = std::min(3.0, 0.2 * best_length);
    if (best_s >= margin && best_s <= best_length - margin)
      sides[best].emplace_back(static_cast<float>(p.x), static_cast<float>(p.y));
  }
  std::vector<cv::Vec4f> lines(n);
  for (size_t k = 0; k < n; ++k) {
    if (sides[k].size() < 2) return polygon;
    lines[k] = trimmedLine(evenlyThinned(std::move(sides[k])));
  }
  std::vector<cv::Point2d> fitted(n);
  for (size_t k = 0; k < n; ++k) {
    const auto corner = crossing(lines[(k + n - 1) % n], lines[k]);
    if (!corner ||
        cv::norm(*corner - polygon[k]) > 0.3 * cv::norm(polygon[(k + 1) % n] - polygon[k]) + 3)
      return polygon;
    fitted[k] = *corner;
  }
  return fitted;
}

// Largest distance of a corner from the template mapped by the least-squares homography, as
// a fraction of sqrt(image area).
double shapeErrorOf(const std::array<cv::Point2d, 8>& corners) {
  std::vector<cv::Point2d> model, image(corners.begin(), corners.end());
  for (const Vec3& p : padModel()) model.emplace_back(p.x(), p.y());
  const cv::Mat H = cv::findHomography(model, image, 0);
  if (H.empty()) return 1e9;
  std::vector<cv::Point2d> mapped;
  cv::perspectiveTransform(model, mapped, H);
  double worst = 0;
  for (size_t i = 0; i < mapped.size(); ++i)
    worst = std::max(worst, cv::norm(mapped[i] - image[i]));
  const double area = std::abs(signedArea(image)) / 2;
  return worst / std::sqrt(std::max(area, 1.0));
}

// Mean grey of a ring around the T minus the mean inside it.
double contrastOf(const cv::Mat& grey, const std::array<cv::Point2d, 8>& corners) {
  std::vector<cv::Point> polygon;
  for (const auto& c : corners) polygon.emplace_back(cvRound(c.x), cvRound(c.y));
  const cv::Rect box = cv::boundingRect(polygon);
  const int grow = std::max(3, std::min(box.width, box.height) / 6);
  // Only the pad's neighbourhood: the ring reaches `grow` beyond it.
  const cv::Rect roi = cv::Rect(box.x - grow - 2, box.y - grow - 2, box.width + 2 * grow + 4,
                                box.height + 2 * grow + 4) &
                       cv::Rect(0, 0, grey.cols, grey.rows);
  const cv::Mat patch = grey(roi);
  cv::Mat inside = cv::Mat::zeros(patch.size(), CV_8UC1);
  for (auto& p : polygon) p -= roi.tl();
  cv::fillPoly(inside, std::vector<std::vector<cv::Point>>{polygon}, 255);
  cv::Mat ring;
  cv::dilate(inside, ring, cv::getStructuringElement(cv::MORPH_RECT, {2 * grow + 1, 2 * grow + 1}));
  cv::Mat eroded;
  cv::erode(inside, eroded, cv::getStructuringElement(cv::MORPH_RECT, {3, 3}));
  ring -= inside;
  if (cv::countNonZero(ring) == 0 || cv::countNonZero(eroded) == 0) return 0;
  return cv::mean(patch, ring)[0] - cv::mean(patch, eroded)[0];
}

// The region's outline again at a threshold of its own: midway between its median grey and
// that of a ring around it. A threshold for the whole image sits where the image's largest
// areas part (deck and sea), and the deck's darker specks then join the T.
std::vector<cv::Point> localContour(const cv::Mat& grey, const std::vector<cv::Point>& coarse) {
  const cv::Rect box = cv::boundingRect(coarse);
  const int grow = std::max(4, std::max(box.width, box.height) / 3);
  const cv::Rect roi =
      cv::Rect(box.x - grow, box.y - grow, box.width + 2 * grow, box.height + 2 * grow) &
      cv::Rect(0, 0, grey.cols, grey.rows);
  const cv::Mat patch = grey(roi);
  cv::Mat inside = cv::Mat::zeros(patch.size(), CV_8UC1);
  cv::drawContours(inside, std::vector<std::vector<cv::Point>>{coarse}, 0, 255, cv::FILLED,
                   cv::LINE_8, cv::noArray(), INT_MAX, -roi.tl());
  cv::Mat core, ring;
  const cv::Mat k3 = cv::getStructuringElement(cv::MORPH_RECT, {3, 3});
  cv::erode(inside, core, k3);
  cv::dilate(inside, ring,
             cv::getStructuringElement(cv::MORPH_RECT, {2 * grow / 2 + 1, 2 * grow / 2 + 1}));
  cv::subtract(ring, inside, ring);
  // A histogram's median (the lower of the middle two): one pass, no copy of the pixels.
  auto medianUnder = [&](const cv::Mat& mask) {
    std::array<int, 256> histogram{};
    int count = 0;
    for (int y = 0; y < patch.rows; ++y) {
      const uint8_t* grey_row = patch.ptr<uint8_t>(y);
      const uint8_t* mask_row = mask.ptr<uint8_t>(y);
      for (int x = 0; x < patch.cols; ++x) {
        if (mask_row[x] != 0) {
          ++histogram[grey_row[x]];
          ++count;
        }
      }
    }
    if (count == 0) return -1;
    for (int value = 0, seen = 0; value < 256; ++value) {
      seen += histogram[value];
      if (2 * seen >= count) return value;
    }
    return 255;
  };
  const int dark = medianUnder(core), light = medianUnder(ring);
  if (dark < 0 || light < 0 || light <= dark) return {};
  cv::Mat binary;
  cv::threshold(patch, binary, (dark + light) / 2.0, 255, cv::THRESH_BINARY_INV);
  cv::morphologyEx(binary, binary, cv::MORPH_OPEN, k3);
  std::vector<std::vector<cv::Point>> found;
  cv::findContours(binary, found, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_NONE, roi.tl());
  // The outline that overlaps the coarse region most: the one with the largest area inside it.
  const cv::Moments m = cv::moments(coarse);
  if (m.m00 <= 0) return {};
  const cv::Point2f centroid(static_cast<float>(m.m10 / m.m00), static_cast<float>(m.m01 / m.m00));
  const std::vector<cv::Point>* best = nullptr;
  double best_area = 0;
  for (const auto& c : found) {
    const double area = std::abs(cv::contourArea(c));
    if (area > best_area && (cv::pointPolygonTest(c, centroid, false) >= 0 || area > 0.5 * m.m00)) {
      best_area = area;
      best = &c;
    }
  }
  return best != nullptr ? *best : std::vector<cv::Point>{};
}

struct Candidate {
  std::array<cv::Point2d, 8> corners;
  double shape_error = 0, contrast = 0;
};

// Dark regions of a binarised image as T candidates; the reasons for the ones refused.
// The reason for the refused region that came closest to being the pad (rank: not a T 1, a T
// of the wrong proportions 2, a right T too faint 3).
struct WhyNot {
  int rank = 0;
  std::string text;
  void offer(int r, std::string t) {
    if (r >= rank) {
      rank = r;
      text = std::move(t);
    }
  }
};

void collect(const cv::Mat& grey, const cv::Mat& dark, const DetectorOptions& options,
             std::vector<Candidate>& out, PadDetection& report, WhyNot& why_not) {
  cv::Mat clean;
  const cv::Mat kernel = cv::getStructuringElement(cv::MORPH_RECT, {3, 3});
  cv::morphologyEx(dark, clean, cv::MORPH_OPEN, kernel);
  cv::morphologyEx(clean, clean, cv::MORPH_CLOSE, kernel);
  std::vector<std::vector<cv::Point>> contours;
  cv::findContours(clean, contours, cv::RETR_LIST, cv::CHAIN_APPROX_NONE);
  for (const auto& coarse : contours) {
    if (std::abs(cv::contourArea(coarse)) < options.min_area_px) continue;
    const std::vector<cv::Point> contour = localContour(grey, coarse);
    if (contour.empty()) continue;
    std::vector<cv::Point2d> polygon = eightVertices(contour);
    if (polygon.empty()) continue;
    ++report.candidates;
    if (signedArea(polygon) < 0) std::reverse(polygon.begin(), polygon.end());
    for (int round = 0; round < 3; ++round) polygon = fitSides(contour, polygon);
    const auto ordered = orderTCorners(polygon);
    if (!ordered) {
      why_not.offer(1, "an 8-cornered shape that is not a T");
      continue;
    }
    Candidate candidate{*ordered, shapeErrorOf(*ordered), 0};
    if (candidate.shape_error > options.max_shape_error) {
      why_not.offer(2, "a T of the wrong proportions (shape error " +
                           std::to_string(candidate.shape_error).substr(0, 5) + ")");
      continue;
    }
    candidate.contrast = contrastOf(grey, candidate.corners);
    if (candidate.contrast < options.min_contrast) {
      why_not.offer(3, "a T too faint against its surroundings");
      continue;
    }
    out.push_back(candidate);
  }
}

}  // namespace

double padShapeError(const std::array<cv::Point2d, 8>& corners) { return shapeErrorOf(corners); }

std::optional<std::array<cv::Point2d, 8>> orderTCorners(const std::vector<cv::Point2d>& polygon) {
  if (polygon.size() != 8) return std::nullopt;
  std::array<bool, 8> concave{};
  int concave_count = 0;
  for (int i = 0; i < 8; ++i) {
    const cv::Point2d in = polygon[i] - polygon[(i + 7) % 8];
    const cv::Point2d out = polygon[(i + 1) % 8] - polygon[i];
    concave[i] = cross(in, out) < 0;  // turning left on a clockwise polygon
    concave_count += concave[i];
  }
  if (concave_count != 2) return std::nullopt;
  for (int d = 0; d < 8; ++d) {
    if (!concave[d] || !concave[(d + 3) % 8]) continue;
    std::array<cv::Point2d, 8> named;
    for (int k = 0; k < 8; ++k) named[k] = polygon[(d + 5 + k) % 8];  // a is 5 after d
    return named;
  }
  return std::nullopt;
}

std::array<cv::Point2d, 8> patentOrder(const std::vector<cv::Point2d>& clockwise) {
  auto startingAt = [&](size_t start) {
    std::array<cv::Point2d, 8> out;
    for (size_t k = 0; k < 8; ++k) out[k] = clockwise[(start + k) % 8];
    return out;
  };
  size_t top = 0, left = 0;
  for (size_t i = 1; i < 8; ++i) {
    if (clockwise[i].y < clockwise[top].y) top = i;
    if (clockwise[i].x < clockwise[left].x) left = i;
  }
  auto order = startingAt(top);
  if (cv::norm(order[1] - order[0]) < cv::norm(order[7] - order[0])) order = startingAt(left);
  return order;
}

namespace {

// One pass of refineCorners on the image as floats.
std::array<cv::Point2d, 8> refineOnce(const cv::Mat& smooth,
                                      const std::array<cv::Point2d, 8>& corners,
                                      PadEdgePoints* edges) {
  if (edges != nullptr) *edges = {};
  auto sample = [&](double x, double y) {
    const int x0 = static_cast<int>(std::floor(x)), y0 = static_cast<int>(std::floor(y));
    if (x0 < 0 || y0 < 0 || x0 + 1 >= smooth.cols || y0 + 1 >= smooth.rows) return -1.0;
    const double fx = x - x0, fy = y - y0;
    const float* r0 = smooth.ptr<float>(y0);
    const float* r1 = smooth.ptr<float>(y0 + 1);
    return (1 - fy) * ((1 - fx) * r0[x0] + fx * r0[x0 + 1]) +
           fy * ((1 - fx) * r1[x0] + fx * r1[x0 + 1]);
  };
  // Each edge as a line: points where the grey changes fastest across it.
  std::array<std::optional<cv::Vec4f>, 8> lines;
  for (int k = 0; k < 8; ++k) {
    const cv::Point2d a = corners[k], b = corners[(k + 1) % 8];
    const double length = cv::norm(b - a);
    if (length < 6) continue;
    const cv::Point2d along = (b - a) / length, normal(-along.y, along.x);
    std::vector<cv::Point2f> points;
    constexpr int kReach = 3;  // pixels either side of the polygon's edge
    // Away from the corners, where a profile across this edge would cross the next one.
    const double margin = std::min(kReach + 1.5, 0.25 * length);
    // Every pixel along the edge, or kMaxEdgePoints spread over a longer one.
    const double step = std::max(1.0, (length - 2 * margin) / (kMaxEdgePoints - 1));
    for (double s = margin; s <= length - margin; s += step) {
      const cv::Point2d p = a + along * s;
      std::array<double, 2 * kReach * 4 + 1> profile{};
      bool inside = true;
      for (int i = 0; i < static_cast<int>(profile.size()) && inside; ++i) {
        const double offset = (i - kReach * 4) * 0.25;
        profile[i] = sample(p.x + normal.x * offset, p.y + normal.y * offset);
        inside = profile[i] >= 0;
      }
      if (!inside) continue;
      int best = -1;
      double best_gradient = 0;
      std::array<double, profile.size()> gradient{};
      for (size_t i = 1; i + 1 < profile.size(); ++i) {
        gradient[i] = std::abs(profile[i + 1] - profile[i - 1]);
        if (gradient[i] > best_gradient) {
          best_gradient = gradient[i];
          best = static_cast<int>(i);
        }
      }
      if (best <= 1 || best + 2 >= static_cast<int>(profile.size())) continue;
      // The edge is where the grey crosses halfway from the deck (outside) to the paint
      // (inside): the level crossing nearest the steepest point, which the texture beside the
      // edge moves less than it moves the peak. The two levels are read 0.75-1.5 px either
      // side, as close as the step allows: still inside the blur, but symmetric, so the
      // halfway level stays right, and the deck's texture has less room to pull it (reading
      // them at 2.25-3 px put 0.5-1.3 deg into the pose at 20 m, 0.2-0.6 here).
      double outside = 0, inside_level = 0;
      for (int i = 6; i < 10; ++i) {
        outside += profile[i] / 4;
        inside_level += profile[profile.size() - 1 - i] / 4;
      }
      if (outside - inside_level < 10) continue;
      const double level = 0.5 * (outside + inside_level);
      std::optional<double> at;
      for (int step = 0; step < 8 && !at; ++step) {
        for (const int i : {best - step, best + step - 1}) {
          if (i < 0 || i + 1 >= static_cast<int>(profile.size()) || at) continue;
          const double u = profile[i] - level, w = profile[i + 1] - level;
          if (u >= 0 && w < 0) at = i + u / (u - w);
        }
      }
      if (!at) continue;
      const double offset = (*at - kReach * 4) * 0.25;
      points.emplace_back(p + normal * offset);
    }
    if (points.size() < 3) continue;
    lines[k] = trimmedLine(points, edges != nullptr ? &(*edges)[k] : nullptr);
  }
  std::array<cv::Point2d, 8> refined = corners;
  for (int k = 0; k < 8; ++k) {
    const auto& in = lines[(k + 7) % 8];
    const auto& out = lines[k];
    if (!in || !out) continue;
    const auto corner = crossing(*in, *out);
    if (corner && cv::norm(*corner - corners[k]) < 3.0) refined[k] = *corner;
  }
  return refined;
}

}  // namespace

std::array<cv::Point2d, 8> refineCorners(const cv::Mat& grey,
                                         const std::array<cv::Point2d, 8>& corners,
                                         PadEdgePoints* edges) {
  cv::Mat image;
  grey.convertTo(image, CV_32F);
  // Until it settles (at most 4 passes): each pass centres the profiles across each edge on
  // the last pass's lines, so the deck's and the paint's levels are read as far from the
  // edge on both sides (a polygon from a threshold can be a pixel or two off).
  std::array<cv::Point2d, 8> refined = corners;
  for (int pass = 0; pass < 4; ++pass) {
    const auto next = refineOnce(image, refined, edges);  // the last pass's edges stay
    double moved = 0;
    for (int k = 0; k < 8; ++k) moved = std::max(moved, cv::norm(next[k] - refined[k]));
    refined = next;
    if (moved < 0.02) break;
  }
  for (int k = 0; k < 8; ++k) {
    if (cv::norm(refined[k] - corners[k]) >= 3.0) refined[k] = corners[k];
  }
  return refined;
}

PadDetection detectPad(const cv::Mat& grey, const DetectorOptions& options) {
  PadDetection result;
  if (grey.empty() || grey.type() != CV_8UC1) {
    result.reason = "no image (or not 8-bit grey)";
    return result;
  }
  std::vector<Candidate> candidates;
  WhyNot why_not;
  // The search on `seen` (the image, or the image reduced by 2: a pixel x there is 2x here).
  const bool reduced = options.reduce == 2;
  cv::Mat seen = grey;
  DetectorOptions search = options;
  if (reduced) {
    cv::pyrDown(grey, seen);
    search.min_area_px /= 4;
  }
  cv::Mat dark;
  cv::threshold(seen, dark, 0, 255, cv::THRESH_BINARY_INV | cv::THRESH_OTSU);
  collect(seen, dark, search, candidates, result, why_not);
  if (candidates.empty()) {
    // Uneven light (a shadow across the pad): a threshold from each pixel's neighbourhood.
    const int block = (std::min(seen.cols, seen.rows) / 6) | 1;
    cv::adaptiveThreshold(seen, dark, 255, cv::ADAPTIVE_THRESH_MEAN_C, cv::THRESH_BINARY_INV, block,
                          15);
    collect(seen, dark, search, candidates, result, why_not);
  }
  if (reduced) {
    for (auto& candidate : candidates) {
      for (auto& corner : candidate.corners) corner *= 2.0;
    }
  }
  if (candidates.empty()) {
    result.reason = result.candidates == 0 ? "no dark region with 8 corners in view"
                                           : "no pad: " + why_not.text;
    return result;
  }
  const auto best = std::min_element(
      candidates.begin(), candidates.end(),
      [](const Candidate& a, const Candidate& b) { return a.shape_error < b.shape_error; });
  result.found = true;
  result.corners =
      options.refine ? refineCorners(grey, best->corners, &result.edges) : best->corners;
  result.shape_error = best->shape_error;
  result.contrast = best->contrast;
  return result;
}

}  // namespace stereomap::landing
