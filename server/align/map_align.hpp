// Aligning two occupancy maps of the same place with no hint: the rigid transform that puts
// map B onto map A (x_A = T_a_b x_B), or a refusal saying why none can be trusted.
//
// How (docs/design/align-plan.md has the choices and their sources):
//  1. Both maps' occupied cells at two search levels (the finest whose cells number at most
//     `max_points`, and the one finer), with normals oriented towards the map's own free
//     space.
//  2. At each level, FPFH features, mutual nearest matches (OpenCV's FLANN), then RANSAC over
//     those matches. RANSAC keeps only its best pose, so it is run again on the
//     matches the poses found so far do not explain: `hypotheses` poses per level, each
//     refined by ICP and scored at the finer level. When their best does not pass the gates,
//     matches among each other's 3 nearest add as many poses (low overlap: more true pairs).
//  3. Each pose is scored by what both maps say: occupied cells that land on the other map's
//     occupied cells agree; those that land in its free space contradict it (unknown space
//     says nothing). The best pose is refined level by level down to the finest voxels.
//  4. Gates, any of which refuses: too little overlap, too many contradictions, a second
//     distinct pose that fits nearly as well (a symmetric room, a repeated pattern), or a
//     match that does not pin a direction of translation (a road, a plain corridor).
// Every random draw is seeded and every parallel step sums in a fixed order: the same maps give
// the same answer, with any number of threads. Open3D supplies the k-d trees and normals; the
// FPFH, RANSAC and ICP are ours, computed as Open3D's but on shared trees and rasters
// (fpfh.hpp, icp.hpp, space_raster.hpp), several times faster.
//
//   auto aligned = align::alignMaps(a, b, {});
//   if (!aligned) error (empty map, different resolutions...);
//   else if (!aligned->found) refused: aligned->reason
//   else aligned->T_a_b, aligned->overlap, aligned->rmse_m
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <string>

#include "common/geometry.hpp"
#include "common/result.hpp"
#include "server/fusion/occupancy_map.hpp"

namespace stereomap::align {

struct AlignOptions {
  // Working level: the finest whose occupied cells number at most this in the larger map.
  size_t max_points = 15000;
  // Refusals. Overlap: the share of the smaller map's occupied voxels (at the working level)
  // with an occupied voxel of the other within one cell after alignment.
  double min_overlap = 0.15;
  // Agreement: agreeing / (agreeing + contradicting) occupied cells, both ways.
  double min_agreement = 0.93;
  // A second pose (further than `distinct_m` or `distinct_deg` from the best) scoring at least
  // this share of the best's score makes the match ambiguous.
  double max_second_ratio = 0.75;
  double distinct_cells = 4.0;  // in working cells
  double distinct_deg = 10.0;
  // Degeneracy: the weakest direction of translation must hold at least this share of the
  // strongest (eigenvalues of the sum of n n^T over the matched cells' normals)...
  double min_constraint_ratio = 0.01;
  // ... and the pose slid 3 cells along it must score less than this share of its own score.
  // Measured (stereomap-bench-align): poses found right 0-0.83 (a road: 0.70-0.83), wrong ones
  // that passed every other gate 0.96-1.11 (a floor and one wall, a road slid along).
  double max_slide = 0.9;
  // Floors and walls agree under a wrong pose in a room like the right one; what stands off
  // them (boxes, edges, clutter) does not. So the cells off each map's large planes that the
  // other map saw (occupied or free) must number at least min_structure_cells, and at least
  // min_structure_agreement of them must agree. Measured (stereomap-bench-align, --only small
  // and a real clip): poses found right 341-9,825 cells (a stretch of a flight in its own room
  // the fewest, 341-1,141; KITTI 432-888), agreement 0.86-1.00
  // (a 1-s stretch of a sim flight the lowest, KITTI 0.94-0.99); a stretch of a room placed in
  // a similar room, every other gate passed, 0.00-0.11; the EuRoC clip (3 clouds: little
  // more than three planes) in a sim room 54 cells, 0.98.
  size_t min_structure_cells = 150;
  double min_structure_agreement = 0.7;
  int hypotheses = 4;  // RANSAC runs per search level
  // When the mutual matches' best pose does not pass, matches among each other's 3 nearest
  // too: more pairs of little overlap found, refusals twice the work. The live aligner, which
  // tries again as a map grows and must not fall behind, goes without.
  bool wider_matches = true;
  uint32_t seed = 1;
  // OpenMP threads of the normals, features, matching, ICP and scores; the answer does not
  // depend on them. The server keeps to one (fusion comes first); the CLI takes every core.
  unsigned threads = 1;
  // Called between steps (what is being done), for progress on long work; may be empty.
  std::function<void(const std::string&)> progress;
};

struct Alignment {
  bool found = false;
  std::string reason;  // why not, when !found
  common::Rigid3 T_a_b = common::Rigid3::identity();
  double overlap = 0;    // 0..1, see AlignOptions::min_overlap
  double agreement = 0;  // 0..1, see AlignOptions::min_agreement
  double rmse_m = 0;     // the finest ICP's inlier RMSE
  // How sure: 1 - (second best score / best score); 1 when no other pose was found.
  double confidence = 0;
  double constraint_ratio = 0;  // see AlignOptions::min_constraint_ratio
  // The score of the pose slid 3 cells along its weakest direction, over its own: near 1
  // when the match does not pin that direction. See AlignOptions::max_slide.
  double slide = 0;
  // See AlignOptions::min_structure_cells and min_structure_agreement.
  size_t structure_cells = 0;
  double structure_agreement = 0;  // 0..1
  double working_cell_m = 0;
  size_t voxels_a = 0, voxels_b = 0;  // occupied, finest
  size_t matches = 0;                 // feature matches RANSAC started from
  int poses_tried = 0;
  double seconds = 0;
  // Where the seconds went (they add up to `seconds`, but for checks and bookkeeping), and
  // how many search levels ran (2: the coarser one's best pose did not pass the gates).
  struct Steps {
    double levels = 0;      // the pyramids, normals and their orientation, kd-trees
    double features = 0;    // FPFH and their matching
    double ransac = 0;      // RANSAC over the matches, and which matches each pose explains
    double hypotheses = 0;  // each pose's ICP at its level and the scoring level, its score
    double judging = 0;     // the gates (scores, constraint, slide), at each level and at the end
    double refining = 0;    // ICP level by level to the finest voxels, and the RMSE
    int levels_searched = 0;
    std::string first_level_verdict;  // with two levels: why the first one's best was not taken
  } steps;
};

// Errors (kInvalidArgument): a map with fewer than `kMinVoxels` occupied voxels, maps of
// different resolutions. A refusal is not an error: found == false with a reason.
inline constexpr size_t kMinVoxels = 50;
common::Result<Alignment> alignMaps(const fusion::OccupancyMap& a, const fusion::OccupancyMap& b,
                                    const AlignOptions& options);

// "align A B: t ... q ..., overlap O%, rmse E m, S s" or "align A B: none (reason)": the
// line the CLI and the REST answer end with.
std::string alignLine(const std::string& a, const std::string& b, const Alignment& alignment);

}  // namespace stereomap::align
