// The image noise of a grey image, estimated from the image alone: the noise's standard
// deviation in grey levels. Stereo depth noise follows image noise (the matching cost
// amplifies it), so the depth step chooses how hard to smooth from this figure.
//
//   double sigma = imageNoiseSigma(left);  // ~0 on clean images, ~2 on a typical camera
#pragma once

#include <opencv2/core.hpp>

namespace stereomap::camera {

// Immerkær's operator (the difference of two Laplacians, which cancels smooth image content)
// over the flattest tenth of the pixels (by their gradient), without clipped ones: on real
// images texture fills most pixels (foliage, asphalt) and read as noise before (KITTI 1.2-1.8,
// Middlebury 1.0-1.7 grey levels where their flattest parts show 1.0-1.5 and 0.8-1.0).
// CV_8UC1; images smaller than 3x3 give 0. Samples every `step`-th row.
double imageNoiseSigma(const cv::Mat& grey, int step = 2);

}  // namespace stereomap::camera
