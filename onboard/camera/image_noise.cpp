#include "onboard/camera/image_noise.hpp"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <vector>

namespace stereomap::camera {

double imageNoiseSigma(const cv::Mat& grey, int step) {
  CV_Assert(grey.type() == CV_8UC1 && step >= 1);
  if (grey.rows < 3 || grey.cols < 3) return 0;
  // Per pixel: N = [1 -2 1; -2 4 -2; 1 -2 1] (Immerkær: smooth content cancels, white noise
  // of sigma gives a normal response of sigma 6) and the Sobel gradient's size. N is even and
  // Sobel odd, so for white noise the two are independent: choosing pixels by their gradient
  // does not bias the noise read there.
  struct Sample {
    int gradient, response;
  };
  std::vector<Sample> samples;
  samples.reserve(static_cast<size_t>((grey.rows / step + 1) * grey.cols));
  for (int v = 1; v + 1 < grey.rows; v += step) {
    const uint8_t* above = grey.ptr<uint8_t>(v - 1);
    const uint8_t* row = grey.ptr<uint8_t>(v);
    const uint8_t* below = grey.ptr<uint8_t>(v + 1);
    for (int u = 1; u + 1 < grey.cols; ++u) {
      const int a = above[u - 1], b = above[u], c = above[u + 1];
      const int d = row[u - 1], e = row[u], f = row[u + 1];
      const int g = below[u - 1], h = below[u], i = below[u + 1];
      // Clipped pixels (a saturated sky, black shadows) hold no noise.
      const int lowest = std::min({a, b, c, d, e, f, g, h, i});
      const int highest = std::max({a, b, c, d, e, f, g, h, i});
      if (lowest <= 2 || highest >= 253) continue;
      const int gx = (c + 2 * f + i) - (a + 2 * d + g);
      const int gy = (g + 2 * h + i) - (a + 2 * b + c);
      samples.push_back({std::abs(gx) + std::abs(gy),
                         std::abs(a - 2 * b + c - 2 * d + 4 * e - 2 * f + g - 2 * h + i)});
    }
  }
  if (samples.empty()) return 0;
  // The flattest tenth: texture and edges, in most pixels of a real image (foliage, grass,
  // asphalt), would read as noise; where the image is flattest what is left is noise.
  const size_t flat = std::max<size_t>(1, samples.size() / 10);
  std::nth_element(samples.begin(), samples.begin() + static_cast<long>(flat - 1), samples.end(),
                   [](const Sample& x, const Sample& y) { return x.gradient < y.gradient; });
  double sum = 0;
  for (size_t k = 0; k < flat; ++k) sum += samples[k].response;
  // The mean magnitude of a normal of sigma 6 is 6 sigma sqrt(2 / pi).
  return std::sqrt(M_PI / 2) * (sum / static_cast<double>(flat)) / 6.0;
}

}  // namespace stereomap::camera
