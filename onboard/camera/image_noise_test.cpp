#include "onboard/camera/image_noise.hpp"

#include <gtest/gtest.h>

#include <opencv2/imgproc.hpp>

#include <cmath>

namespace stereomap::camera {
namespace {

// A textured scene (smooth waves and a hard edge, as texture and edges in real images) with
// white noise of `sigma` grey levels.
cv::Mat scene(double sigma) {
  cv::Mat image(480, 640, CV_32FC1);
  for (int v = 0; v < image.rows; ++v) {
    for (int u = 0; u < image.cols; ++u) {
      image.at<float>(v, u) = static_cast<float>(
          110 + 40 * std::sin(u * 0.05) * std::cos(v * 0.07) + (u > 320 ? 30 : 0));
    }
  }
  cv::Mat noise(image.size(), CV_32FC1);
  cv::setRNGSeed(3);
  cv::randn(noise, 0.0, sigma);
  cv::Mat grey;
  cv::Mat noisy = image + noise;
  noisy.convertTo(grey, CV_8UC1);
  return grey;
}

TEST(ImageNoise, EstimatesWhiteNoiseThroughTexture) {
  EXPECT_LT(imageNoiseSigma(scene(0)), 0.5);  // 8-bit rounding alone: about 0.3
  for (const double sigma : {2.0, 4.0, 8.0}) {
    EXPECT_NEAR(imageNoiseSigma(scene(sigma)), sigma, 0.1 * sigma) << "sigma " << sigma;
  }
}

TEST(ImageNoise, FineTextureOverMostOfTheImageIsNotNoise) {
  // Foliage-like texture (random, a few pixels across, +-20 grey levels) over 80 % of the
  // image, a flat band below, and white noise: read as the noise, not as texture. The median
  // over all pixels (the estimator before) read 2.0 for sigma 1 and 2.75 for sigma 2 here.
  cv::Mat texture(480, 640, CV_32FC1);
  cv::setRNGSeed(5);
  cv::randn(texture, 0.0, 20.0);
  cv::GaussianBlur(texture, texture, cv::Size(), 0.7);
  texture.rowRange(384, 480).setTo(0);
  for (const double sigma : {1.0, 2.0}) {
    cv::Mat noise(texture.size(), CV_32FC1);
    cv::randn(noise, 0.0, sigma);
    cv::Mat grey;
    cv::Mat(texture + noise + 120.0).convertTo(grey, CV_8UC1);
    EXPECT_NEAR(imageNoiseSigma(grey), sigma, 0.15 * sigma) << "sigma " << sigma;
  }
}

TEST(ImageNoise, ClippedPixelsHoldNoNoise) {
  // A saturated sky over half the image: it is not where the noise is read.
  cv::Mat grey = scene(2.0);
  grey.rowRange(0, 240).setTo(255);
  EXPECT_NEAR(imageNoiseSigma(grey), 2.0, 0.2);
}

TEST(ImageNoise, TinyImagesGiveZero) {
  EXPECT_EQ(imageNoiseSigma(cv::Mat(2, 2, CV_8UC1, cv::Scalar(7))), 0.0);
}

}  // namespace
}  // namespace stereomap::camera
