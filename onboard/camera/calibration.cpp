#include "onboard/camera/calibration.hpp"

#include <chrono>
#include <fstream>
#include <sstream>

#include "common/forked_write.hpp"

namespace stereomap::camera {

namespace fs = std::filesystem;
using common::Error;
using common::ErrorCode;
using common::makeError;
using common::Result;
using common::Status;

namespace {

constexpr const char* kFormat = "stereomap-stereo-calibration";

Error fieldError(const std::string& file, const std::string& field, const std::string& what) {
  return makeError(ErrorCode::kInvalidArgument, file + ": " + field + " " + what);
}

bool allFinite(const cv::Mat& m) { return m.empty() || cv::checkRange(m, true, nullptr); }

// Reads a matrix node as CV_64F with the given shape (rows x cols; cols 0 = any length
// row/column vector), or an error naming the field.
Result<cv::Mat> readMatrix(const cv::FileStorage& fs, const std::string& file,
                           const std::string& field, int rows, int cols) {
  const cv::FileNode node = fs[field];
  if (node.empty()) return fieldError(file, field, "is missing");
  // OpenCV allocates rows x cols before it reads the data: a mangled "cols" made it ask for
  // 51 GB (found by fuzzing, tests/fuzz/corpus/calibration/huge-cols). Ours are 4x4 at most.
  if (node.isMap()) {
    const cv::FileNode node_rows = node["rows"], node_cols = node["cols"];
    if (!node_rows.isInt() || !node_cols.isInt() || static_cast<int>(node_rows) < 0 ||
        static_cast<int>(node_rows) > 64 || static_cast<int>(node_cols) < 0 ||
        static_cast<int>(node_cols) > 64) {
      return fieldError(file, field, "has rows or cols that are not whole numbers in 0..64");
    }
  }
  cv::Mat m;
  try {
    node >> m;
  } catch (const cv::Exception&) {
    return fieldError(file, field, "is not a matrix");
  }
  if (m.empty()) return fieldError(file, field, "is empty or not a matrix");
  m.convertTo(m, CV_64F);
  if (cols == 0) {
    if (m.rows != 1 && m.cols != 1) return fieldError(file, field, "must be a vector");
    m = m.reshape(1, 1);
  } else if (m.rows != rows || m.cols != cols) {
    return fieldError(file, field,
                      "must be " + std::to_string(rows) + "x" + std::to_string(cols) + ", is " +
                          std::to_string(m.rows) + "x" + std::to_string(m.cols));
  }
  if (!allFinite(m)) return fieldError(file, field, "has a non-finite value");
  return m;
}

// A calibration file is a few kB; anything this large is not one, and would be slow to parse.
constexpr std::uintmax_t kMaxCalibrationBytes = 1 << 20;
// OpenCV parses a few-kB file in milliseconds; this leaves room for a loaded, sanitised run.
constexpr std::chrono::seconds kParseDeadline{5};

// OpenCV 4.6's YAML parser loops forever on some damaged files (found by fuzzing:
// tests/fuzz/corpus/calibration/opencv-yaml-hang, 20 bytes). There is no way to stop it from
// the same process, so a forked child parses the file first, with a deadline; only a file the
// child got through is parsed here (the same bytes: the parser is deterministic).
common::Status parsesInTime(const fs::path& path) {
  auto child = common::ForkedWrite::start([&path](std::ostream&) {
    try {
      cv::FileStorage storage(path.string(), cv::FileStorage::READ);
    } catch (...) {
      // Errors are the parent's to report, from its own parse.
    }
    return true;
  });
  // Without fork (no memory for it, or a process limit) the file is parsed unguarded.
  if (!child) return common::Ok{};
  auto done = child->finish(kParseDeadline);
  if (done) return common::Ok{};
  if (done.error().code == ErrorCode::kUnavailable) {
    return makeError(ErrorCode::kCorrupt, path.string() +
                                              ": OpenCV's YAML/XML parser did not finish within " +
                                              std::to_string(kParseDeadline.count()) +
                                              " s (a damaged file makes it loop)");
  }
  // The child died in the parser: this process would too.
  return makeError(
      ErrorCode::kCorrupt,
      path.string() + ": OpenCV's YAML/XML parser failed on it (" + done.error().message + ")");
}

Result<cv::FileStorage> openStorage(const fs::path& path) {
  std::error_code error;
  if (!fs::is_regular_file(path, error)) {
    return error && error != std::errc::no_such_file_or_directory
               ? makeError(ErrorCode::kIo, path.string() + ": cannot read: " + error.message())
               : makeError(ErrorCode::kNotFound, path.string() + ": no such calibration file");
  }
  if (const auto bytes = fs::file_size(path, error); !error && bytes > kMaxCalibrationBytes) {
    return makeError(ErrorCode::kTooLarge,
                     path.string() + ": " + std::to_string(bytes) +
                         " bytes is too large for a calibration file (at most 1 MiB)");
  }
  if (auto parsed = parsesInTime(path); !parsed) return parsed.error();
  try {
    cv::FileStorage storage(path.string(), cv::FileStorage::READ);
    if (!storage.isOpened()) {
      return makeError(ErrorCode::kCorrupt, path.string() + ": cannot be parsed as YAML/XML");
    }
    // OpenCV throws from storage["key"] when the top level is not a map (a list, a scalar):
    // found by fuzzing (tests/fuzz/corpus/calibration/top-level-list).
    if (!storage.root().isMap()) {
      return makeError(ErrorCode::kCorrupt,
                       path.string() + ": its top level is not a map of named fields");
    }
    return storage;
  } catch (const cv::Exception& e) {
    return makeError(ErrorCode::kCorrupt,
                     path.string() + ": cannot be parsed as YAML/XML (" + e.err + ")");
  } catch (const std::exception& e) {
    // OpenCV 4.6's parser also lets std::length_error out of a mangled file (found by
    // fuzzing: tests/fuzz/corpus/calibration/parser-length-error).
    return makeError(ErrorCode::kCorrupt,
                     path.string() + ": cannot be parsed as YAML/XML (" + e.what() + ")");
  }
}

Result<cv::Size> readSize(const cv::FileStorage& storage, const std::string& file,
                          const std::string& width_key, const std::string& height_key) {
  const cv::FileNode w = storage[width_key], h = storage[height_key];
  if (w.empty() && h.empty()) return cv::Size();
  if (!w.isInt() || !h.isInt() || static_cast<int>(w) <= 0 || static_cast<int>(h) <= 0) {
    return fieldError(file, width_key + "/" + height_key, "must be positive integers");
  }
  return cv::Size(static_cast<int>(w), static_cast<int>(h));
}

// Both cameras' intrinsics (names differ between formats) into `c`.
common::Status readIntrinsics(const cv::FileStorage& storage, const std::string& file,
                              const char* K_left, const char* D_left, const char* K_right,
                              const char* D_right, StereoCalibration& c) {
  for (auto [K_name, D_name, camera] :
       {std::tuple{K_left, D_left, &c.left}, std::tuple{K_right, D_right, &c.right}}) {
    auto K = readMatrix(storage, file, K_name, 3, 3);
    if (!K) return K.error();
    auto D = readMatrix(storage, file, D_name, 1, 0);
    if (!D) return D.error();
    *camera = {cv::Matx33d(*K), *D};
  }
  return common::Ok{};
}

common::Status readExtrinsics(const cv::FileStorage& storage, const std::string& file,
                              StereoCalibration& c) {
  auto R = readMatrix(storage, file, "R", 3, 3);
  if (!R) return R.error();
  auto T = readMatrix(storage, file, "T", 1, 0);
  if (!T) return T.error();
  if (T->total() != 3) return fieldError(file, "T", "must have 3 elements");
  c.R = cv::Matx33d(*R);
  c.T = cv::Vec3d(T->at<double>(0), T->at<double>(1), T->at<double>(2));
  return common::Ok{};
}

// OpenCV's stereo_calib files: intrinsics (M1 D1 M2 D2) and extrinsics (R T), possibly
// split over intrinsics.yml and extrinsics.yml.
Result<StereoCalibration> readOpenCvStereoCalib(const cv::FileStorage& storage,
                                                const fs::path& path) {
  const std::string file = path.string();
  StereoCalibration c;
  c.source = file;
  if (auto s = readIntrinsics(storage, file, "M1", "D1", "M2", "D2", c); !s) return s.error();
  if (storage["R"].empty() && storage["T"].empty()) {
    const fs::path beside = path.parent_path() / "extrinsics.yml";
    auto extrinsics = openStorage(beside);
    if (!extrinsics) {
      return fieldError(file, "R/T", "are missing (and no extrinsics.yml beside it)");
    }
    c.source += " + " + beside.string();
    if (auto s = readExtrinsics(*extrinsics, beside.string(), c); !s) return s.error();
  } else if (auto s = readExtrinsics(storage, file, c); !s) {
    return s.error();
  }
  auto size = readSize(storage, file, "image_width", "image_height");
  if (!size) return size.error();
  c.image_size = *size;
  return c;
}

Result<StereoCalibration> readOurs(const cv::FileStorage& storage, const fs::path& path) {
  const std::string file = path.string();
  StereoCalibration c;
  c.source = file;
  auto size = readSize(storage, file, "image_width", "image_height");
  if (!size) return size.error();
  if (size->area() == 0) return fieldError(file, "image_width/image_height", "are missing");
  c.image_size = *size;
  if (auto s = readIntrinsics(storage, file, "K_left", "D_left", "K_right", "D_right", c); !s) {
    return s.error();
  }
  if (auto s = readExtrinsics(storage, file, c); !s) return s.error();
  return c;
}

// The four numbers after `key:` ... of a KITTI calib.txt line "P1: 12 numbers".
Result<cv::Matx34d> kittiProjection(const std::string& text, const std::string& file,
                                    const std::string& key) {
  std::istringstream lines(text);
  for (std::string line; std::getline(lines, line);) {
    if (line.rfind(key + ":", 0) != 0) continue;
    std::istringstream numbers(line.substr(key.size() + 1));
    cv::Matx34d P;
    for (int i = 0; i < 12; ++i) {
      std::string token;
      if (!(numbers >> token)) return fieldError(file, key, "has fewer than 12 numbers");
      try {
        size_t used = 0;
        P.val[i] = std::stod(token, &used);
        if (used != token.size()) throw std::invalid_argument(token);
      } catch (const std::exception&) {
        return fieldError(file, key, "has a non-number '" + token + "'");
      }
      if (!std::isfinite(P.val[i])) return fieldError(file, key, "has a non-finite value");
    }
    return P;
  }
  return fieldError(file, key, "line is missing");
}

Result<cv::Mat> yamlVector(const cv::FileStorage& storage, const std::string& file,
                           const std::string& field, size_t length) {
  const cv::FileNode node = storage[field];
  if (node.empty()) return fieldError(file, field, "is missing");
  if (!node.isSeq()) return fieldError(file, field, "must be a list");
  std::vector<double> values;
  for (const auto& item : node) {
    if (!item.isReal() && !item.isInt()) return fieldError(file, field, "has a non-number");
    values.push_back(static_cast<double>(item));
  }
  if (length != 0 && values.size() != length) {
    return fieldError(
        file, field,
        "must have " + std::to_string(length) + " numbers, has " + std::to_string(values.size()));
  }
  cv::Mat m = cv::Mat(values, true).reshape(1, 1);
  if (!allFinite(m)) return fieldError(file, field, "has a non-finite value");
  return m;
}

struct EurocCamera {
  CameraIntrinsics intrinsics;
  cv::Size size;
  cv::Matx44d T_BS;
};

Result<EurocCamera> readEurocCamera(const fs::path& path) {
  const std::string file = path.string();
  auto storage = openStorage(path);
  if (!storage) return storage.error();
  EurocCamera camera;
  auto intrinsics = yamlVector(*storage, file, "intrinsics", 4);
  if (!intrinsics) return intrinsics.error();
  const double* k = intrinsics->ptr<double>();
  camera.intrinsics.K = cv::Matx33d(k[0], 0, k[2], 0, k[1], k[3], 0, 0, 1);
  const std::string model = (*storage)["distortion_model"].empty()
                                ? ""
                                : static_cast<std::string>((*storage)["distortion_model"]);
  if (model != "radial-tangential") {
    return fieldError(file, "distortion_model", "must be radial-tangential (got '" + model + "')");
  }
  auto distortion = yamlVector(*storage, file, "distortion_coefficients", 4);
  if (!distortion) return distortion.error();
  camera.intrinsics.distortion = *distortion;
  auto resolution = yamlVector(*storage, file, "resolution", 2);
  if (!resolution) return resolution.error();
  camera.size = cv::Size(static_cast<int>(resolution->at<double>(0)),
                         static_cast<int>(resolution->at<double>(1)));
  const cv::FileNode T_BS = (*storage)["T_BS"];
  if (T_BS.empty()) return fieldError(file, "T_BS", "is missing");
  if (!T_BS.isMap() || !T_BS["data"].isSeq()) {
    return fieldError(file, "T_BS", "must be a map with rows, cols and data");
  }
  std::vector<double> values;
  for (const auto& item : T_BS["data"]) values.push_back(static_cast<double>(item));
  if (values.size() != 16) return fieldError(file, "T_BS.data", "must have 16 numbers");
  for (double v : values) {
    if (!std::isfinite(v)) return fieldError(file, "T_BS.data", "has a non-finite value");
  }
  camera.T_BS = cv::Matx44d(values.data());
  return camera;
}

common::Rigid3 toRigid(const cv::Matx44d& T) {
  Eigen::Matrix3d R;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) R(r, c) = T(r, c);
  }
  return {common::Quat(R).normalized(), common::Vec3(T(0, 3), T(1, 3), T(2, 3))};
}

}  // namespace

bool StereoCalibration::isRectified() const {
  auto noDistortion = [](const cv::Mat& d) { return d.empty() || cv::countNonZero(d) == 0; };
  return noDistortion(left.distortion) && noDistortion(right.distortion) &&
         cv::norm(left.K, right.K, cv::NORM_INF) < 1e-9 &&
         cv::norm(R, cv::Matx33d::eye(), cv::NORM_INF) < 1e-12 && T[0] < 0 &&
         std::abs(T[1]) < 1e-12 && std::abs(T[2]) < 1e-12;
}

Status validateCalibration(const StereoCalibration& c) {
  const std::string& file = c.source.empty() ? std::string("calibration") : c.source;
  for (const auto& [name, cam] : {std::pair{"left", &c.left}, std::pair{"right", &c.right}}) {
    const std::string K = std::string("K_") + name;
    if (!allFinite(cv::Mat(cam->K))) return fieldError(file, K, "has a non-finite value");
    if (cam->K(0, 0) <= 0 || cam->K(1, 1) <= 0) {
      return fieldError(file, K, "must have positive focal lengths");
    }
    if (cam->K(2, 0) != 0 || cam->K(2, 1) != 0 || cam->K(2, 2) != 1) {
      return fieldError(file, K, "must have a last row of 0 0 1");
    }
    const size_t n = cam->distortion.total();
    if (n != 0 && n != 4 && n != 5 && n != 8 && n != 12 && n != 14) {
      return fieldError(file, std::string("D_") + name,
                        "must have 4, 5, 8, 12 or 14 coefficients, has " + std::to_string(n));
    }
    if (!allFinite(cam->distortion)) {
      return fieldError(file, std::string("D_") + name, "has a non-finite value");
    }
  }
  if (!allFinite(cv::Mat(c.R)) || !allFinite(cv::Mat(c.T))) {
    return fieldError(file, "R/T", "have a non-finite value");
  }
  const double orthogonality = cv::norm(c.R * c.R.t(), cv::Matx33d::eye(), cv::NORM_INF);
  if (orthogonality > 1e-4 || cv::determinant(c.R) < 0) {
    return fieldError(file, "R", "is not a rotation matrix");
  }
  if (c.baseline() <= 0) return fieldError(file, "T", "is zero: the cameras must be apart");
  if (c.image_size.width < 0 || c.image_size.height < 0) {
    return fieldError(file, "image size", "is negative");
  }
  return common::Ok{};
}

Result<StereoCalibration> readKittiCalibration(const fs::path& path) {
  const std::string file = path.string();
  std::ifstream in(path);
  if (!in) return makeError(ErrorCode::kNotFound, file + ": cannot open the KITTI calib.txt");
  std::stringstream text;
  text << in.rdbuf();
  auto P0 = kittiProjection(text.str(), file, "P0");
  if (!P0) return P0.error();
  auto P1 = kittiProjection(text.str(), file, "P1");
  if (!P1) return P1.error();
  const cv::Matx33d K0 = P0->get_minor<3, 3>(0, 0), K1 = P1->get_minor<3, 3>(0, 0);
  if (cv::norm(K0, K1, cv::NORM_INF) > 1e-6) {
    return fieldError(file, "P1", "has other intrinsics than P0: the pair is not rectified");
  }
  if (K0(0, 0) <= 0) return fieldError(file, "P0", "has a non-positive focal length");
  const double baseline = -(*P1)(0, 3) / K0(0, 0);
  if (!(baseline > 0)) {
    return fieldError(file, "P1", "must have P1[0,3] = -fx * baseline < 0 (right camera on +x)");
  }
  StereoCalibration c;
  c.source = file;
  c.left.K = c.right.K = K0;
  c.T = cv::Vec3d(-baseline, 0, 0);
  if (auto status = validateCalibration(c); !status) return status.error();
  return c;
}

Result<StereoCalibration> readEurocCalibration(const fs::path& cam0_yaml,
                                               const fs::path& cam1_yaml) {
  auto cam0 = readEurocCamera(cam0_yaml);
  if (!cam0) return cam0.error();
  auto cam1 = readEurocCamera(cam1_yaml);
  if (!cam1) return cam1.error();
  if (cam0->size != cam1->size) {
    return fieldError(cam1_yaml.string(), "resolution", "differs from " + cam0_yaml.string());
  }
  StereoCalibration c;
  c.source = cam0_yaml.string() + " + " + cam1_yaml.string();
  c.image_size = cam0->size;
  c.left = cam0->intrinsics;
  c.right = cam1->intrinsics;
  // p_cam1 = inv(T_BS1) * T_BS0 * p_cam0.
  const cv::Matx44d T_C1C0 = cam1->T_BS.inv() * cam0->T_BS;
  c.R = T_C1C0.get_minor<3, 3>(0, 0);
  c.T = cv::Vec3d(T_C1C0(0, 3), T_C1C0(1, 3), T_C1C0(2, 3));
  c.T_body_left = toRigid(cam0->T_BS);
  if (auto status = validateCalibration(c); !status) return status.error();
  return c;
}

Result<StereoCalibration> readCalibration(const fs::path& path) {
  if (!fs::is_regular_file(path)) {
    return makeError(ErrorCode::kNotFound, path.string() + ": no such calibration file");
  }
  {
    std::ifstream in(path);
    std::string first;
    std::getline(in, first);
    if (first.rfind("P0:", 0) == 0) return readKittiCalibration(path);
  }
  auto storage = openStorage(path);
  if (!storage) return storage.error();
  Result<StereoCalibration> calibration = makeError(ErrorCode::kInvalidArgument, "");
  const cv::FileNode format = (*storage)["format"];
  if (!format.empty() && format.isString() && static_cast<std::string>(format) == kFormat) {
    calibration = readOurs(*storage, path);
  } else if (!(*storage)["M1"].empty()) {
    calibration = readOpenCvStereoCalib(*storage, path);
  } else {
    return makeError(ErrorCode::kInvalidArgument,
                     path.string() + ": not a known calibration format (expected 'format: " +
                         kFormat + "', OpenCV stereo_calib's M1/D1/M2/D2, or KITTI P0/P1 lines)");
  }
  if (!calibration) return calibration;
  if (auto status = validateCalibration(*calibration); !status) return status.error();
  return calibration;
}

Status writeCalibration(const fs::path& path, const StereoCalibration& c) {
  if (auto status = validateCalibration(c); !status) return status;
  try {
    cv::FileStorage out(path.string(), cv::FileStorage::WRITE);
    if (!out.isOpened()) return makeError(ErrorCode::kIo, path.string() + ": cannot write");
    out << "format" << kFormat;
    out << "image_width" << c.image_size.width << "image_height" << c.image_size.height;
    // An empty distortion is written as five zeros so that every reader finds the field.
    auto distortion = [](const cv::Mat& d) {
      return d.empty() ? cv::Mat(cv::Mat::zeros(1, 5, CV_64F)) : d;
    };
    out << "K_left" << cv::Mat(c.left.K) << "D_left" << distortion(c.left.distortion);
    out << "K_right" << cv::Mat(c.right.K) << "D_right" << distortion(c.right.distortion);
    out << "R" << cv::Mat(c.R) << "T" << cv::Mat(c.T);
    out << "baseline" << c.baseline();
  } catch (const cv::Exception& e) {
    return makeError(ErrorCode::kIo, path.string() + ": cannot write (" + e.err + ")");
  }
  return common::Ok{};
}

}  // namespace stereomap::camera
