#include "onboard/camera/image_noise.hpp"

#include <algorithm>
#include <array>
#include <cstdlib>

namespace stereomap::camera {

double imageNoiseSigma(const cv::Mat& grey, int step) {
  CV_Assert(grey.type() == CV_8UC1 && step >= 1);
  if (grey.rows < 3 || grey.cols < 3) return 0;
  // |I * N| with N = [1 -2 1; -2 4 -2; 1 -2 1], counted in a histogram (the response of 8-bit
  // images is an integer within +-4080), whose median gives the estimate.
  constexpr int kRange = 4 * 255 * 4 + 1;
  std::array<uint32_t, kRange> counts{};
  uint64_t total = 0;
  for (int v = 1; v + 1 < grey.rows; v += step) {
    const uint8_t* above = grey.ptr<uint8_t>(v - 1);
    const uint8_t* row = grey.ptr<uint8_t>(v);
    const uint8_t* below = grey.ptr<uint8_t>(v + 1);
    for (int u = 1; u + 1 < grey.cols; ++u) {
      const int response = above[u - 1] - 2 * above[u] + above[u + 1] - 2 * row[u - 1] +
                           4 * row[u] - 2 * row[u + 1] + below[u - 1] - 2 * below[u] + below[u + 1];
      ++counts[static_cast<size_t>(std::abs(response))];
      ++total;
    }
  }
  // The median magnitude, interpolated inside its bin (bin k > 0 holds magnitudes within
  // half a level of k; bin 0 those below 0.5).
  const double half = total / 2.0;
  uint64_t below = 0;
  int bin = 0;
  while (bin < kRange - 1 && below + counts[static_cast<size_t>(bin)] < half) {
    below += counts[static_cast<size_t>(bin++)];
  }
  const double lower = bin == 0 ? 0.0 : bin - 0.5, width = bin == 0 ? 0.5 : 1.0;
  const double in_bin = counts[static_cast<size_t>(bin)];
  const double median = lower + (in_bin > 0 ? width * (half - below) / in_bin : 0.0);
  // For white noise sigma the response is normal with sigma 6 (the kernel's squares sum to
  // 36), and the median of its magnitude is 0.6745 of that.
  return median / (0.6745 * 6.0);
}

}  // namespace stereomap::camera
