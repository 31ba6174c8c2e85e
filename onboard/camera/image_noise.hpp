// The image noise of a grey image, estimated from the image alone: the noise's standard
// deviation in grey levels. Stereo depth noise follows image noise (the matching cost
// amplifies it), so the depth step chooses how hard to smooth from this figure.
//
//   double sigma = imageNoiseSigma(left);  // ~0 on clean images, ~2 on a typical camera
#pragma once

#include <opencv2/core.hpp>

namespace stereomap::camera {

// Immerkær's operator (the difference of two Laplacians, which cancels smooth image content)
// with a median instead of a mean, so that texture and edges in the minority of pixels do not
// count as noise. CV_8UC1; images smaller than 3x3 give 0. Samples every `step`-th row.
double imageNoiseSigma(const cv::Mat& grey, int step = 2);

}  // namespace stereomap::camera
