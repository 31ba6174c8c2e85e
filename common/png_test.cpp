#include "common/png.hpp"

#include <gtest/gtest.h>

#include <opencv2/imgcodecs.hpp>

namespace stereomap::common {
namespace {

TEST(Png, OpenCvReadsBackEveryPixel) {
  const uint32_t width = 37, height = 11;  // odd sizes: no row padding assumed anywhere
  std::vector<uint8_t> pixels(size_t{width} * height);
  for (size_t i = 0; i < pixels.size(); ++i) pixels[i] = static_cast<uint8_t>((i * 7919) % 256);
  const std::string png = encodeGreyPng(pixels, width, height);
  ASSERT_FALSE(png.empty());
  const std::vector<uint8_t> bytes(png.begin(), png.end());
  const cv::Mat image = cv::imdecode(bytes, cv::IMREAD_UNCHANGED);
  ASSERT_FALSE(image.empty()) << "OpenCV could not read the PNG";
  ASSERT_EQ(image.type(), CV_8UC1);
  ASSERT_EQ(image.cols, static_cast<int>(width));
  ASSERT_EQ(image.rows, static_cast<int>(height));
  for (uint32_t y = 0; y < height; ++y) {
    for (uint32_t x = 0; x < width; ++x) {
      ASSERT_EQ(image.at<uint8_t>(y, x), pixels[y * width + x]) << x << "," << y;
    }
  }
}

TEST(Png, RefusesSizesThatDoNotMatch) {
  EXPECT_TRUE(encodeGreyPng({}, 0, 0).empty());
  EXPECT_TRUE(encodeGreyPng(std::vector<uint8_t>(10), 3, 3).empty());
}

}  // namespace
}  // namespace stereomap::common
