// Fuzz target: calibration files as stereomap-onboard and stereomap-depth read them
// (onboard/camera/calibration): our YAML, OpenCV's stereo_calib pair (intrinsics.yml beside
// extrinsics.yml), KITTI's calib.txt and EuRoC's two sensor.yaml. The first byte picks the
// reader; the rest is the file, or two files separated by a NUL byte. A file that is read
// must hold a calibration that passes validateCalibration.
#include "onboard/camera/calibration.hpp"
#include "tests/fuzz/fuzz_input.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace stereomap;
  const auto& dir = fuzz::scratch();
  // Each input on its own: a file left by the one before (extrinsics.yml) must not be read.
  for (const auto& entry : std::filesystem::directory_iterator(dir.path())) {
    std::filesystem::remove(entry.path());
  }
  fuzz::FuzzInput in(data, size);
  const uint8_t reader = in.byte() % 4;
  const std::string_view first = in.until('\0');
  const std::string_view second = in.restText();
  common::Result<camera::StereoCalibration> read =
      common::makeError(common::ErrorCode::kInvalidArgument, "");
  switch (reader) {
    case 0:
      read = camera::readCalibration(dir.write("calibration.yaml", first));
      break;
    case 1:
      dir.write("extrinsics.yml", second);
      read = camera::readCalibration(dir.write("intrinsics.yml", first));
      break;
    case 2:
      read = camera::readKittiCalibration(dir.write("calib.txt", first));
      break;
    default:
      read = camera::readEurocCalibration(dir.write("cam0.yaml", first),
                                          dir.write("cam1.yaml", second));
      break;
  }
  if (read && !camera::validateCalibration(*read)) __builtin_trap();
  return 0;
}
