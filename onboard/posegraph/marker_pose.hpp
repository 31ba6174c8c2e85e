// Rigid-body pose from known 3D points (markers on a vehicle seen by a motion-capture
// system, or any model points with measured positions): T_world_body such that
// world_i ~ T_world_body * model_i.
//   leastSquaresPose: the closed form that minimises the sum of squared distances
//     (Horn/Umeyama; Eigen::umeyama without scaling); 3 or more points, not all on a line.
//     The default.
//   vectorCrossPose: the pose-graph paper's vector-cross (VC) method (eqs. 10-14) for 4
//     markers: A_1 = P3 - P1, A_2 = P4 - P2 (normalised), B = A_1 x A_2 (normalised),
//     R = D_w D_m^-1 with D = (A_1, A_2, B), the translation from the point where the lines
//     P1P3 and P2P4 cross. Measured lines do not meet: their closest points' midpoint is used,
//     and R is projected onto the rotations (the paper's D_w D_m^-1 is only a rotation
//     without noise).
//   bodyFrameFromMarkers: the paper's body frame (eqs. 2-9): origin at the markers' centroid,
//     x along P1 -> P3, z the normal of the plane P1 P2 P3, y = z x x.
#pragma once

#include <array>
#include <optional>
#include <vector>

#include "common/geometry.hpp"

namespace stereomap::posegraph {

using Markers = std::array<common::Vec3, 4>;

std::optional<common::Rigid3> leastSquaresPose(const std::vector<common::Vec3>& model,
                                               const std::vector<common::Vec3>& world);

std::optional<common::Rigid3> vectorCrossPose(const Markers& model, const Markers& world);

// T_world_body of the frame eqs. 2-9 build from four measured markers; nullopt when P1, P2,
// P3 are (nearly) on one line.
std::optional<common::Rigid3> bodyFrameFromMarkers(const Markers& world);

}  // namespace stereomap::posegraph
