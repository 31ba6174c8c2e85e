// Pose graphs in g2o's text format, the format the SLAM field's benchmark graphs and tools
// share (../shared/data/posegraph/README.md): read with every fault named by its line, written
// so that every number reads back exactly (an
// SE(2) angle to its last bit or so: it is held as a rotation).
//
//   auto graph = readG2o("parking-garage.g2o");   // Result<G2oGraph>
//   writeG2o("solved.g2o", *graph);                // the same graph, its vertices as they are now
//
// Lines understood: `VERTEX_SE3:QUAT id x y z qx qy qz qw`, `EDGE_SE3:QUAT i j x y z qx qy qz qw`
// + the 21 upper-triangular entries of the 6x6 information (translation first, then rotation),
// `VERTEX_SE2 id x y theta`, `EDGE_SE2 i j x y theta` + 6 entries, `FIX id ...`, comments (#) and
// blank lines. A file holds SE(3) or SE(2) lines, not both. A file may hold no vertex at all (only
// edges): its vertices are then made from the edges' ids, at the identity (`has_estimates`
// false), and a solver must find a start (chordal initialisation).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "common/geometry.hpp"
#include "common/result.hpp"
#include "onboard/posegraph/se3.hpp"

namespace stereomap::posegraph {

struct G2oVertex {
  int64_t id = 0;
  common::Rigid3 T_world_vertex;  // 2D: z = 0, a rotation about z
};

// An SE(2) graph's information (x, y, theta) sits in the 6x6 at the places of (x, y, rz): rows
// and columns 0, 1 and 5; the others are zero.
inline constexpr int kSe2Places[3] = {0, 1, 5};
struct G2oEdge {
  int64_t from = 0, to = 0;  // vertex ids
  common::Rigid3 T_from_to;  // the measured pose of `to` in `from`'s frame
  Mat6 information;          // g2o's order: translation, then rotation; symmetric, its blocks
                             // positive definite, the whole too unless `indefinite`
  int line = 0;              // where it was read (0: made in memory)
  bool indefinite = false;   // the whole matrix is not positive definite (InformationUse::kBlocks)
};

struct G2oGraph {
  int dimension = 3;           // 3: SE(3) lines, 2: SE(2) lines
  bool has_estimates = false;  // the file gave vertex lines
  std::vector<G2oVertex> vertices;
  std::vector<G2oEdge> edges;
  std::vector<int64_t> fixed;         // ids named by FIX lines
  std::vector<std::string> warnings;  // what was read other than as written, each naming its line
};

// What a reader asks of each edge's information matrix. Its translation and rotation blocks
// must be positive definite in every case. Real graphs carry edges whose whole matrix is
// indefinite only through the coupling of translation and rotation (SE-Sync's cubicle.g2o,
// line 5,753: translation z with roll 84,022 against diagonals of 10).
enum class InformationUse {
  kWhole,    // the whole matrix weighs the error (--weights file): an indefinite one is refused
  kBlocks,   // only the blocks are used (SE-Sync's isotropic kappa and tau): the coupling is kept
             // as written, and such an edge is marked `indefinite`
  kNearest,  // like kWhole, but an indefinite matrix is replaced by its nearest positive definite
             // matrix (eigenvalues raised to 1e-9 of the largest), with a warning naming the line
};
struct G2oReadOptions {
  InformationUse information = InformationUse::kWhole;
};

// The largest file readG2o reads (a graph of millions of edges is a few hundred MB).
inline constexpr uint64_t kMaxG2oBytes = uint64_t{1} << 30;

// Reads and checks a whole file (a regular file of at most kMaxG2oBytes, else kInvalidArgument
// or kTooLarge): an error (kInvalidArgument, or kIo/kNotFound for the file)
// names the line and what is wrong with it: an unknown tag, a missing or extra field, a number
// that is not finite, a quaternion far from unit length (within 1 % it is normalised), an
// information matrix not positive definite as `options` asks, a duplicate vertex id, an edge from a
// vertex to itself or to a vertex the file does not define, SE(2) and SE(3) lines in one file.
common::Result<G2oGraph> readG2o(const std::string& path, const G2oReadOptions& options = {});
// The same from text in memory (`name` is what errors call it).
common::Result<G2oGraph> parseG2o(const std::string& text, const std::string& name = "g2o",
                                  const G2oReadOptions& options = {});

// Vertex lines (with the vertices' poses), edge lines and FIX lines, in the graph's dimension,
// every number in the shortest form that reads back exactly. kIo when it cannot be written.
std::string formatG2o(const G2oGraph& graph);
common::Status writeG2o(const std::string& path, const G2oGraph& graph);

}  // namespace stereomap::posegraph
