// Finding the landing patent's black T-shaped pad in a grey image (section 2 of
// ../shared/PAPERS.md): binarise (Otsu, then an adaptive threshold for uneven light), clean
// up with morphology, take contours, fit each with a polygon of 8 vertices, keep the one whose
// shape is a T (exactly two concave corners, three apart) and maps onto the pad template
// through one homography (stricter than the patent's histogram match: the T's proportions,
// not only its area, must agree), name its corners a..h from its structure (any rotation),
// and refine each corner to sub-pixel as the crossing of its two edges, each fitted to
// sub-pixel edge points along it.
//
//   const PadDetection found = detectPad(left);
//   if (found) use(found.corners);              // a..h, as sim::padCorners() / padModel()
//   else log(found.reason);
#pragma once

#include <array>
#include <optional>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "common/geometry.hpp"

namespace stereomap::landing {

// The pad's corners a..h in the pad frame (metres; z = 0), the patent's coordinates: x along
// the T's bar, y down its stem, z = x cross y into the deck; clockwise seen from above,
// starting at the bar's corner a.
const std::array<common::Vec3, 8>& padModel();

// Sub-pixel points along each of the pad's 8 edges in an image: edge k runs from corner k to
// corner k + 1 (a-b, b-c, ..., h-a). At most kMaxEdgePoints on an edge, spread evenly along
// it: at close range an edge spans hundreds of pixels, and the line fits, the corners'
// refinement and the pose (one residual per point) would grow with it past the frame's time.
inline constexpr int kMaxEdgePoints = 128;
using PadEdgePoints = std::array<std::vector<cv::Point2f>, 8>;

struct DetectorOptions {
  // Smaller dark regions are not looked at (the T, 6 m^2, covers about 900 px^2 at 40 m with
  // f = 492 px).
  double min_area_px = 120;
  // Largest distance of a corner from the template mapped by the best homography, as a
  // fraction of the square root of the pad's image area (the sim's T at 11-28 m with noise:
  // 0.006-0.031; its short-stemmed T-like mark is refused).
  double max_shape_error = 0.04;
  // Mean grey inside the T at least this much darker than a ring around it.
  double min_contrast = 25;
  bool refine = true;  // sub-pixel corners from the edges (false: the polygon's vertices)
  // Find the T on the image reduced by 2 (1: as it is); the corners are then refined on the
  // whole image. At close range the pad fills the view, and thresholds, contours and their
  // fits grow with it: PadTracker asks for 2 when the pad was last seen large.
  int reduce = 1;
};

struct PadDetection {
  bool found = false;
  std::string reason;                    // why not, when not found
  std::array<cv::Point2d, 8> corners{};  // a..h
  PadEdgePoints edges;                   // the points the corners' edges were fitted to
  double shape_error = 0;                // as DetectorOptions::max_shape_error
  double contrast = 0;
  int candidates = 0;  // contours with 8 vertices that were checked
  explicit operator bool() const { return found; }
};

PadDetection detectPad(const cv::Mat& grey, const DetectorOptions& options = {});

// Names 8 polygon vertices a..h from the T's structure: clockwise in the image (the pad is
// seen from above, never mirrored), d and g the two concave corners. Empty when the polygon
// is not T-shaped.
std::optional<std::array<cv::Point2d, 8>> orderTCorners(const std::vector<cv::Point2d>& polygon);

// The patent's ordering: start at the vertex with the smallest image y, go clockwise; when
// |ab| < |ah| start again at the vertex with the smallest x. Right only for a pad seen upright
// (the bar at the top), kept for comparison: detectPad orders by structure.
std::array<cv::Point2d, 8> patentOrder(const std::vector<cv::Point2d>& clockwise);

// Largest distance of a corner from the template mapped by the least-squares homography, as a
// fraction of the square root of the pad's image area (DetectorOptions::max_shape_error).
double padShapeError(const std::array<cv::Point2d, 8>& corners);

// Sub-pixel corners: each of the 8 edges fitted as a line to the points where the grey crosses
// halfway between deck and paint across it, neighbouring lines crossed. Keeps a corner as it
// was where its edges cannot be fitted. `edges`: the points kept on each edge.
std::array<cv::Point2d, 8> refineCorners(const cv::Mat& grey,
                                         const std::array<cv::Point2d, 8>& corners,
                                         PadEdgePoints* edges = nullptr);

}  // namespace stereomap::landing
