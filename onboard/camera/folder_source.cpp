// folder:DIR, left/right image pairs in a folder with a calibration file.
#include "onboard/camera/dataset_source.hpp"

#include <algorithm>

#include "onboard/camera/detail/recorded_source.hpp"

namespace stereomap::camera {

namespace fs = std::filesystem;
using detail::Clock;
using detail::FrameFiles;

common::Result<std::unique_ptr<FrameSource>> openFolder(const fs::path& dir,
                                                        const DatasetOptions& options) {
  if (!fs::is_directory(dir)) {
    return common::makeError(common::ErrorCode::kNotFound,
                             "folder:" + dir.string() + ": no such folder");
  }
  // Pairs: left/ and right/ subfolders with the same file names, or left*/right* files.
  std::vector<FrameFiles> frames;
  auto isImage = [](const fs::path& p) {
    std::string ext = p.extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(), ::tolower);
    return ext == ".png" || ext == ".jpg" || ext == ".jpeg" || ext == ".bmp" || ext == ".pgm";
  };
  std::vector<fs::path> lefts;
  if (fs::is_directory(dir / "left") && fs::is_directory(dir / "right")) {
    for (const auto& e : fs::directory_iterator(dir / "left")) {
      if (isImage(e.path())) lefts.push_back(e.path());
    }
    std::sort(lefts.begin(), lefts.end());
    for (const auto& l : lefts) frames.push_back({l, dir / "right" / l.filename()});
  } else {
    for (const auto& e : fs::directory_iterator(dir)) {
      if (isImage(e.path()) && e.path().filename().string().rfind("left", 0) == 0) {
        lefts.push_back(e.path());
      }
    }
    std::sort(lefts.begin(), lefts.end());
    for (const auto& l : lefts) {
      frames.push_back({l, dir / ("right" + l.filename().string().substr(4))});
    }
  }
  for (size_t i = 0; i < frames.size(); ++i) {
    frames[i].stamp_ns = static_cast<int64_t>(static_cast<double>(i) / options.rate_hz * 1e9);
  }
  auto calibration = detail::calibrationOr(options, [&]() -> common::Result<StereoCalibration> {
    for (const char* name :
         {"calibration.yaml", "calibration.yml", "calib.txt", "intrinsics.yml"}) {
      if (fs::exists(dir / name)) return readCalibration(dir / name);
    }
    return common::makeError(
        common::ErrorCode::kNotFound,
        "folder:" + dir.string() +
            ": no calibration.yaml, calib.txt or intrinsics.yml in it; pass --calib");
  });
  if (!calibration) return calibration.error();
  return detail::makeRecorded("folder:" + dir.string(), std::move(frames), *calibration,
                              std::nullopt, Clock::kFromFirstFrame, options);
}

}  // namespace stereomap::camera
