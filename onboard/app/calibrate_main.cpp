// stereomap-calibrate: stereo calibration from chessboard image pairs, written in
// stereomap's calibration format for `stereomap-onboard --source folder:DIR`.
#include <glob.h>
#include <CLI/CLI.hpp>

#include <cstdio>
#include <regex>

#include "common/cli.hpp"
#include "onboard/camera/chessboard.hpp"

namespace {

std::vector<std::filesystem::path> expand(const std::string& pattern) {
  glob_t found{};
  std::vector<std::filesystem::path> paths;
  if (::glob(pattern.c_str(), 0, nullptr, &found) == 0) {
    for (size_t i = 0; i < found.gl_pathc; ++i) paths.emplace_back(found.gl_pathv[i]);
  }
  globfree(&found);
  return paths;  // glob sorts its matches
}

}  // namespace

int main(int argc, char** argv) {
  using namespace stereomap::camera;
  CLI::App app{"stereomap-calibrate: stereo calibration from chessboard image pairs"};
  std::string left_glob, right_glob, board = "9x6", out;
  double square = 1.0;
  app.add_option("--left", left_glob, "Left images, a quoted glob such as 'left*.jpg'")->required();
  app.add_option("--right", right_glob, "Right images, paired with the left ones in sorted order")
      ->required();
  app.add_option("--board", board, "Inner corners of the chessboard, COLSxROWS")
      ->capture_default_str();
  app.add_option("--square", square, "Edge of one square in metres (sets the baseline's unit)")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app.add_option("--out", out, "Calibration file to write (stereomap YAML)")->required();
  if (auto exit_code = stereomap::common::parseCommandLine(app, argc, argv)) return *exit_code;

  std::smatch match;
  const std::regex board_format(R"((\d+)x(\d+))");
  if (!std::regex_match(board, match, board_format)) {
    std::fprintf(stderr, "--board '%s' must be COLSxROWS of inner corners, e.g. 9x6\n",
                 board.c_str());
    return 2;
  }
  const auto left = expand(left_glob), right = expand(right_glob);
  if (left.empty() || right.empty()) {
    std::fprintf(stderr, "no images match --%s '%s'\n", left.empty() ? "left" : "right",
                 (left.empty() ? left_glob : right_glob).c_str());
    return 2;
  }
  if (left.size() != right.size()) {
    std::fprintf(stderr, "--left matches %zu images but --right matches %zu: they must pair up\n",
                 left.size(), right.size());
    return 2;
  }
  std::vector<std::pair<std::filesystem::path, std::filesystem::path>> pairs;
  for (size_t i = 0; i < left.size(); ++i) pairs.emplace_back(left[i], right[i]);

  const ChessboardOptions options{{std::stoi(match[1]), std::stoi(match[2])}, square};
  auto report = calibrateFromChessboards(pairs, options, [](size_t done, size_t total) {
    std::fprintf(stderr, "\rfinding corners: %zu/%zu", done, total);
    if (done == total) std::fprintf(stderr, "\n");
  });
  if (!report) {
    std::fprintf(stderr, "calibration failed: %s\n", report.error().message.c_str());
    return 1;
  }

  std::printf("%-28s %-28s %10s %10s\n", "left", "right", "RMS left", "RMS right");
  for (const auto& view : report->views) {
    if (view.used) {
      std::printf("%-28s %-28s %7.3f px %7.3f px\n", view.left.filename().c_str(),
                  view.right.filename().c_str(), view.rms_left_px, view.rms_right_px);
    } else {
      std::printf("%-28s %-28s  skipped: %s\n", view.left.filename().c_str(),
                  view.right.filename().c_str(), view.reason.c_str());
    }
  }
  const auto& c = report->calibration;
  std::printf("\nviews used: %zu of %zu\n", report->used_views(), report->views.size());
  std::printf("RMS reprojection error: left %.4f px, right %.4f px, stereo %.4f px\n",
              report->rms_left_px, report->rms_right_px, report->rms_stereo_px);
  std::printf("focal length: left fx %.2f fy %.2f, right fx %.2f fy %.2f px\n", c.left.K(0, 0),
              c.left.K(1, 1), c.right.K(0, 0), c.right.K(1, 1));
  std::printf("baseline: %.6f m (with --square %.6g m)\n", c.baseline(), square);
  if (auto written = writeCalibration(out, c); !written) {
    std::fprintf(stderr, "%s\n", written.error().message.c_str());
    return 1;
  }
  std::printf("written: %s\n", out.c_str());
  return 0;
}
