#include "common/trajectory.hpp"

#include <fmt/format.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <iterator>
#include <sstream>

#include "common/files.hpp"

namespace stereomap::common {

namespace {

Error bad(const std::filesystem::path& path, size_t line, const std::string& what) {
  return makeError(ErrorCode::kInvalidArgument,
                   path.string() + ":" + std::to_string(line) + ": " + what);
}

// The numbers of a line (commas count as spaces); false at the first word that is not one.
bool numbersOf(std::string text, std::vector<double>& out) {
  for (char& c : text) c = c == ',' ? ' ' : c;
  std::istringstream in(text);
  out.clear();
  std::string word;
  while (in >> word) {
    char* end = nullptr;
    const double value = std::strtod(word.c_str(), &end);
    if (end == word.c_str() || *end != '\0') return false;
    out.push_back(value);
  }
  return true;
}

bool allFinite(const std::vector<double>& values) {
  for (double v : values)
    if (!std::isfinite(v)) return false;
  return true;
}

}  // namespace

Result<Trajectory> readTrajectory(const std::filesystem::path& path,
                                  const std::filesystem::path& kitti_times,
                                  TrajectoryFormat* format) {
  std::ifstream in(path);
  if (!in) return makeError(ErrorCode::kNotFound, "cannot read " + path.string());
  std::vector<double> times;
  if (!kitti_times.empty()) {
    std::ifstream t(kitti_times);
    if (!t) return makeError(ErrorCode::kNotFound, "cannot read " + kitti_times.string());
    for (double value; t >> value;) times.push_back(value);
  }
  Trajectory trajectory;
  std::string line;
  std::vector<double> v;
  size_t columns = 0;
  for (size_t number = 1; std::getline(in, line); ++number) {
    const size_t first = line.find_first_not_of(" \t\r");
    if (first == std::string::npos || line[first] == '#') continue;
    if (!numbersOf(line, v)) return bad(path, number, "not a list of numbers");
    if (columns == 0) {
      if (v.size() != 8 && v.size() != 12) {
        return bad(path, number,
                   std::to_string(v.size()) +
                       " numbers: expected 8 (TUM: t tx ty tz qx qy qz qw) or 12 (KITTI 3x4)");
      }
      columns = v.size();
    }
    if (v.size() != columns) {
      return bad(path, number,
                 std::to_string(v.size()) + " numbers where earlier lines have " +
                     std::to_string(columns));
    }
    if (!allFinite(v)) return bad(path, number, "a number is not finite");
    StampedPose pose;
    if (columns == 8) {
      pose.t = v[0];
      pose.pose.translation = Vec3(v[1], v[2], v[3]);
      const Quat q(v[7], v[4], v[5], v[6]);
      if (!isUnitQuaternion(q, 1e-2)) return bad(path, number, "the quaternion is not unit length");
      pose.pose.rotation = q.normalized();
    } else {
      const size_t index = trajectory.size();
      if (!times.empty() && index >= times.size()) {
        return bad(path, number, "more poses than times in " + kitti_times.string());
      }
      pose.t = times.empty() ? static_cast<double>(index) : times[index];
      Eigen::Matrix3d R;
      R << v[0], v[1], v[2], v[4], v[5], v[6], v[8], v[9], v[10];
      if ((R.transpose() * R - Eigen::Matrix3d::Identity()).norm() > 1e-2 || R.determinant() < 0) {
        return bad(path, number, "the 3x3 part is not a rotation");
      }
      pose.pose.rotation = Quat(R).normalized();
      pose.pose.translation = Vec3(v[3], v[7], v[11]);
    }
    trajectory.push_back(pose);
  }
  if (trajectory.empty())
    return makeError(ErrorCode::kInvalidArgument, path.string() + ": no poses");
  if (format != nullptr) *format = columns == 8 ? TrajectoryFormat::kTum : TrajectoryFormat::kKitti;
  return trajectory;
}

std::string tumText(const Trajectory& trajectory) {
  std::string text;
  for (const auto& p : trajectory) {
    const auto& t = p.pose.translation;
    const auto& q = p.pose.rotation;
    // No fixed buffer: a position of 1e300 m is written whole (a 256-byte line cut it).
    fmt::format_to(std::back_inserter(text),
                   "{:.9f} {:.6f} {:.6f} {:.6f} {:.9f} {:.9f} {:.9f} {:.9f}\n", p.t, t.x(), t.y(),
                   t.z(), q.x(), q.y(), q.z(), q.w());
  }
  return text;
}

std::string kittiText(const Trajectory& trajectory) {
  std::string text;
  char line[320];
  for (const auto& p : trajectory) {
    const Eigen::Matrix3d R = p.pose.rotation.toRotationMatrix();
    const auto& t = p.pose.translation;
    std::snprintf(line, sizeof(line),
                  "%.9e %.9e %.9e %.9e %.9e %.9e %.9e %.9e %.9e %.9e %.9e %.9e\n", R(0, 0), R(0, 1),
                  R(0, 2), t.x(), R(1, 0), R(1, 1), R(1, 2), t.y(), R(2, 0), R(2, 1), R(2, 2),
                  t.z());
    text += line;
  }
  return text;
}

Status writeText(const std::filesystem::path& path, const std::string& text) {
  return writeFileAtomically(path, text);
}

}  // namespace stereomap::common
