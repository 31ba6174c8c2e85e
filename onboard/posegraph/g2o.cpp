#include "onboard/posegraph/g2o.hpp"

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <string_view>
#include <unordered_map>

#include "common/files.hpp"

namespace stereomap::posegraph {

namespace {

using common::ErrorCode;

// A field as an error names it: quoted, at most 40 bytes, any byte that is not printable
// ASCII written as \xNN (a binary file's bytes never reach the terminal).
std::string quoted(std::string_view field) {
  std::string out(1, '\'');
  for (const char c : field.substr(0, 40)) {
    const auto byte = static_cast<unsigned char>(c);
    if (byte >= 0x20 && byte < 0x7f) {
      out += c;
    } else {
      char escaped[5];
      std::snprintf(escaped, sizeof(escaped), "\\x%02x", byte);
      out += escaped;
    }
  }
  out += '\'';
  return out;
}

std::vector<std::string_view> splitFields(std::string_view line) {
  std::vector<std::string_view> fields;
  size_t i = 0;
  while (i < line.size()) {
    while (i < line.size() && (line[i] == ' ' || line[i] == '\t' || line[i] == '\r')) ++i;
    const size_t start = i;
    while (i < line.size() && line[i] != ' ' && line[i] != '\t' && line[i] != '\r') ++i;
    if (i > start) fields.push_back(line.substr(start, i - start));
  }
  return fields;
}

class LineReader {
 public:
  LineReader(const std::string& name, int line, const std::vector<std::string_view>& fields)
      : name_(name), line_(line), fields_(fields) {}

  std::string where() const { return name_ + " line " + std::to_string(line_); }
  common::Error fault(const std::string& what) const {
    return common::makeError(ErrorCode::kInvalidArgument,
                             name_ + " line " + std::to_string(line_) + ": " + what);
  }
  // The fields after the tag must be exactly `count`.
  bool expect(size_t count, std::string* why) const {
    if (fields_.size() - 1 == count) return true;
    *why = std::string(fields_[0]) + " takes " + std::to_string(count) + " numbers, the line has " +
           std::to_string(fields_.size() - 1);
    return false;
  }
  bool id(size_t index, int64_t* out, std::string* why) const {
    const auto field = fields_[index];
    const auto [end, error] = std::from_chars(field.data(), field.data() + field.size(), *out);
    if (error == std::errc() && end == field.data() + field.size()) return true;
    *why = quoted(field) + " is not a vertex id (a whole number)";
    return false;
  }
  bool number(size_t index, double* out, std::string* why) const {
    const auto field = fields_[index];
    const char* begin = field.data();
    if (!field.empty() && field[0] == '+') ++begin;  // from_chars takes no plus sign
    const auto [end, error] = std::from_chars(begin, field.data() + field.size(), *out);
    if (error == std::errc() && end == field.data() + field.size() && std::isfinite(*out)) {
      return true;
    }
    *why = "field " + std::to_string(index + 1) + " " + quoted(field) + " is not a finite number";
    return false;
  }
  bool numbers(size_t first, size_t count, double* out, std::string* why) const {
    for (size_t k = 0; k < count; ++k) {
      if (!number(first + k, out + k, why)) return false;
    }
    return true;
  }

 private:
  const std::string& name_;
  int line_;
  const std::vector<std::string_view>& fields_;
};

// x y z qx qy qz qw, the quaternion normalised when within 1 % of unit length (and kept as it
// is when unit to its rounding: normalising again would move its last bits, and a graph
// written by formatG2o must read back to the bit).
bool readSe3(const LineReader& reader, size_t first, common::Rigid3* out, std::string* why) {
  double v[7];
  if (!reader.numbers(first, 7, v, why)) return false;
  const Eigen::Quaterniond q(v[6], v[3], v[4], v[5]);
  if (std::abs(q.norm() - 1.0) > 0.01) {
    *why = "the quaternion (" + std::to_string(v[3]) + ", " + std::to_string(v[4]) + ", " +
           std::to_string(v[5]) + ", " + std::to_string(v[6]) + ") is not of unit length";
    return false;
  }
  const bool unit = std::abs(q.squaredNorm() - 1.0) <= 1e-15;
  *out = {unit ? q : q.normalized(), Eigen::Vector3d(v[0], v[1], v[2])};
  return true;
}

bool readSe2(const LineReader& reader, size_t first, common::Rigid3* out, std::string* why) {
  double v[3];
  if (!reader.numbers(first, 3, v, why)) return false;
  *out = {Eigen::Quaterniond(Eigen::AngleAxisd(v[2], Eigen::Vector3d::UnitZ())),
          Eigen::Vector3d(v[0], v[1], 0.0)};
  return true;
}

bool positiveDefinite(const Eigen::MatrixXd& m) {
  return Eigen::LLT<Eigen::MatrixXd>(m).info() == Eigen::Success;
}

// The nearest symmetric positive definite matrix in the Frobenius norm (Higham 1988): the
// eigenvalues below a floor raised to it. The floor, 1e-9 of the largest, keeps the matrix
// invertible without inventing certainty the file did not give.
Eigen::MatrixXd nearestPositiveDefinite(const Eigen::MatrixXd& m, double* relative_change) {
  const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eigen(m);
  const Eigen::VectorXd values = eigen.eigenvalues();
  const double floor = std::max(values.maxCoeff(), 0.0) * 1e-9 + 1e-300;
  const Eigen::MatrixXd nearest =
      eigen.eigenvectors() * values.cwiseMax(floor).asDiagonal() * eigen.eigenvectors().transpose();
  *relative_change = (nearest - m).norm() / m.norm();
  return 0.5 * (nearest + nearest.transpose());
}

// The upper triangle, row by row, of an n x n information matrix placed at `places` (the
// first n - rotation entries are translation, the rest rotation), checked as `use` asks.
bool readInformation(const LineReader& reader, size_t first, int n, const int* places,
                     InformationUse use, G2oEdge* edge, std::vector<std::string>* warnings,
                     std::string* why) {
  Mat6& out = edge->information;
  out.setZero();
  size_t field = first;
  for (int r = 0; r < n; ++r) {
    for (int c = r; c < n; ++c) {
      double value = 0;
      if (!reader.number(field++, &value, why)) return false;
      out(places[r], places[c]) = value;
      out(places[c], places[r]) = value;
    }
  }
  Eigen::MatrixXd block(n, n);
  for (int r = 0; r < n; ++r) {
    for (int c = 0; c < n; ++c) block(r, c) = out(places[r], places[c]);
  }
  const int translation = n == 6 ? 3 : 2, rotation = n - translation;
  const bool translation_usable = positiveDefinite(block.topLeftCorner(translation, translation));
  const bool rotation_usable = positiveDefinite(block.bottomRightCorner(rotation, rotation));
  if (!translation_usable || !rotation_usable) {
    *why = std::string("the information matrix's ") +
           (translation_usable ? "rotation" : "translation") +
           " block is not positive definite (no weighting can use it)";
    return false;
  }
  edge->indefinite = !positiveDefinite(block);
  if (!edge->indefinite || use == InformationUse::kBlocks) return true;
  if (use == InformationUse::kWhole) {
    *why =
        "the information matrix is not positive definite (only through its coupling of "
        "translation and rotation: its blocks are; --weights isotropic reads it, and "
        "--indefinite nearest uses the nearest positive definite matrix)";
    return false;
  }
  double change = 0;
  const Eigen::MatrixXd nearest = nearestPositiveDefinite(block, &change);
  for (int r = 0; r < n; ++r) {
    for (int c = 0; c < n; ++c) out(places[r], places[c]) = nearest(r, c);
  }
  edge->indefinite = false;
  char away[32];
  std::snprintf(away, sizeof(away), "%.3g", 100.0 * change);
  warnings->push_back(reader.where() +
                      ": the information matrix is not positive definite; its nearest positive "
                      "definite matrix is used (" +
                      away + " % away in the Frobenius norm)");
  return true;
}

constexpr int kSpatial[6] = {0, 1, 2, 3, 4, 5};

}  // namespace

common::Result<G2oGraph> parseG2o(const std::string& text, const std::string& name,
                                  const G2oReadOptions& options) {
  G2oGraph graph;
  int dimension = 0, dimension_line = 0;
  std::unordered_map<int64_t, int> vertex_line;  // id -> the line that defined it
  std::vector<int64_t> edge_ids;                 // ids the edges name, checked at the end
  int line_number = 0;
  size_t begin = 0;
  while (begin < text.size()) {
    size_t end = text.find('\n', begin);
    if (end == std::string::npos) end = text.size();
    const std::string_view line(text.data() + begin, end - begin);
    begin = end + 1;
    ++line_number;
    const auto fields = splitFields(line);
    if (fields.empty() || fields[0][0] == '#') continue;
    const LineReader reader(name, line_number, fields);
    const std::string_view tag = fields[0];
    std::string why;
    const bool se3_vertex = tag == "VERTEX_SE3:QUAT", se2_vertex = tag == "VERTEX_SE2";
    const bool se3_edge = tag == "EDGE_SE3:QUAT", se2_edge = tag == "EDGE_SE2";
    if (tag == "FIX") {
      for (size_t k = 1; k < fields.size(); ++k) {
        int64_t id = 0;
        if (!reader.id(k, &id, &why)) return reader.fault(why);
        graph.fixed.push_back(id);
        edge_ids.push_back(id);
      }
      continue;
    }
    if (!se3_vertex && !se2_vertex && !se3_edge && !se2_edge) {
      return reader.fault(
          "unknown line " + quoted(tag) +
          ": VERTEX_SE3:QUAT, EDGE_SE3:QUAT, VERTEX_SE2, EDGE_SE2 and FIX are read");
    }
    const int line_dimension = se3_vertex || se3_edge ? 3 : 2;
    if (dimension == 0) {
      dimension = line_dimension;
      dimension_line = line_number;
    } else if (dimension != line_dimension) {
      return reader.fault("an SE(" + std::to_string(line_dimension) + ") line in a file of SE(" +
                          std::to_string(dimension) + ") lines (since line " +
                          std::to_string(dimension_line) + ")");
    }
    if (se3_vertex || se2_vertex) {
      G2oVertex vertex;
      if (!reader.expect(se3_vertex ? 8 : 4, &why) || !reader.id(1, &vertex.id, &why) ||
          !(se3_vertex ? readSe3(reader, 2, &vertex.T_world_vertex, &why)
                       : readSe2(reader, 2, &vertex.T_world_vertex, &why))) {
        return reader.fault(why);
      }
      const auto [it, inserted] = vertex_line.emplace(vertex.id, line_number);
      if (!inserted) {
        return reader.fault("vertex " + std::to_string(vertex.id) +
                            " is defined again (first on line " + std::to_string(it->second) + ")");
      }
      graph.vertices.push_back(vertex);
      continue;
    }
    G2oEdge edge;
    edge.line = line_number;
    if (!reader.expect(se3_edge ? 30 : 11, &why) || !reader.id(1, &edge.from, &why) ||
        !reader.id(2, &edge.to, &why) ||
        !(se3_edge ? readSe3(reader, 3, &edge.T_from_to, &why)
                   : readSe2(reader, 3, &edge.T_from_to, &why)) ||
        !readInformation(reader, se3_edge ? 10 : 6, se3_edge ? 6 : 3,
                         se3_edge ? kSpatial : kSe2Places, options.information, &edge,
                         &graph.warnings, &why)) {
      return reader.fault(why);
    }
    if (edge.from == edge.to) {
      return reader.fault("an edge from vertex " + std::to_string(edge.from) + " to itself");
    }
    graph.edges.push_back(edge);
  }
  graph.dimension = dimension == 0 ? 3 : dimension;
  graph.has_estimates = !graph.vertices.empty();
  if (graph.edges.empty() && graph.vertices.empty()) {
    return common::makeError(ErrorCode::kInvalidArgument, name + ": no vertex and no edge");
  }
  if (graph.has_estimates) {
    for (const auto& edge : graph.edges) {
      for (const int64_t id : {edge.from, edge.to}) {
        if (!vertex_line.count(id)) {
          return common::makeError(ErrorCode::kInvalidArgument,
                                   name + " line " + std::to_string(edge.line) + ": vertex " +
                                       std::to_string(id) + " is not defined by any vertex line");
        }
      }
    }
  } else {
    // Only edges: every id they name is a vertex, at the identity until a start is found.
    for (const auto& edge : graph.edges) {
      for (const int64_t id : {edge.from, edge.to}) {
        if (vertex_line.emplace(id, edge.line).second) graph.vertices.push_back({id, {}});
      }
    }
  }
  for (const int64_t id : graph.fixed) {
    if (!vertex_line.count(id)) {
      return common::makeError(
          ErrorCode::kInvalidArgument,
          name + ": FIX names vertex " + std::to_string(id) + ", which is not in the graph");
    }
  }
  return graph;
}

common::Result<G2oGraph> readG2o(const std::string& path, const G2oReadOptions& options) {
  // Read whole: a device or a pipe (/dev/zero) would never end, a huge file would fill memory.
  std::error_code error;
  const auto status = std::filesystem::status(path, error);
  if (!error && status.type() != std::filesystem::file_type::regular &&
      status.type() != std::filesystem::file_type::not_found) {
    return common::makeError(ErrorCode::kInvalidArgument, path + " is not a regular file");
  }
  const auto size = std::filesystem::file_size(path, error);
  if (!error && size > kMaxG2oBytes) {
    return common::makeError(ErrorCode::kTooLarge,
                             path + " has " + std::to_string(size) + " bytes, more than the " +
                                 std::to_string(kMaxG2oBytes) + " a graph may have");
  }
  auto bytes = common::readWholeFile(path);
  if (!bytes) return bytes.error();
  return parseG2o(std::string(bytes->begin(), bytes->end()), path, options);
}

namespace {

void appendNumber(std::string* out, double value) {
  char buffer[32];
  const auto result = std::to_chars(buffer, buffer + sizeof(buffer), value);
  out->push_back(' ');
  out->append(buffer, result.ptr);
}

void appendPose(std::string* out, const common::Rigid3& pose, int dimension) {
  const Eigen::Vector3d& t = pose.translation;
  if (dimension == 2) {
    const Eigen::Matrix3d R = pose.rotation.toRotationMatrix();
    for (double v : {t.x(), t.y(), std::atan2(R(1, 0), R(0, 0))}) appendNumber(out, v);
    return;
  }
  const Eigen::Quaterniond& q = pose.rotation;
  for (double v : {t.x(), t.y(), t.z(), q.x(), q.y(), q.z(), q.w()}) appendNumber(out, v);
}

}  // namespace

std::string formatG2o(const G2oGraph& graph) {
  const bool planar = graph.dimension == 2;
  const int n = planar ? 3 : 6;
  const int* places = planar ? kSe2Places : kSpatial;
  std::string out;
  for (const auto& vertex : graph.vertices) {
    out += planar ? "VERTEX_SE2 " : "VERTEX_SE3:QUAT ";
    out += std::to_string(vertex.id);
    appendPose(&out, vertex.T_world_vertex, graph.dimension);
    out += '\n';
  }
  for (const auto& edge : graph.edges) {
    out += planar ? "EDGE_SE2 " : "EDGE_SE3:QUAT ";
    out += std::to_string(edge.from) + " " + std::to_string(edge.to);
    appendPose(&out, edge.T_from_to, graph.dimension);
    for (int r = 0; r < n; ++r) {
      for (int c = r; c < n; ++c) appendNumber(&out, edge.information(places[r], places[c]));
    }
    out += '\n';
  }
  if (!graph.fixed.empty()) {
    out += "FIX";
    for (const int64_t id : graph.fixed) {
      out += ' ';
      out += std::to_string(id);
    }
    out += '\n';
  }
  return out;
}

common::Status writeG2o(const std::string& path, const G2oGraph& graph) {
  return common::writeFileAtomically(path, formatG2o(graph));
}

}  // namespace stereomap::posegraph
