// A start for a pose graph's local solver near the global optimum: the chordal relaxation of
// the rotations, then the translations (Carlone et al., ICRA 2015; SE-Sync's initialisation).
// The rotations minimise sum kappa |R_j - R_i R~_ij|_F^2 over all 3x3 matrices (a linear
// problem), each then projected onto SO(3) (SO(2) for a planar graph); the translations then
// minimise sum tau |t_j - t_i - R_i t~_ij|^2 with those rotations. Both are sparse linear
// systems solved once; each piece's fixed vertex keeps its pose. Needs no vertex estimate: a
// file with edges only starts here.
//
//   chordalInitialise(problem);   // problem.poses() replaced
#pragma once

#include "common/result.hpp"
#include "onboard/posegraph/graph_problem.hpp"

namespace stereomap::posegraph {

// kInvalidArgument when a system cannot be solved (a graph whose rotations the edges do not
// determine; with one fixed vertex per piece this does not happen).
common::Status chordalInitialise(GraphProblem& problem);

}  // namespace stereomap::posegraph
