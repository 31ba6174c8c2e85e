// Linked into every binary of a ThreadSanitizer build only (cmake/stereomap.cmake): OpenCV runs
// its parallel loops on TBB's threads, and TBB (not instrumented) hands the work over and joins
// it through its own atomics, which ThreadSanitizer cannot see. Every image OpenCV (or our one
// parallel_for_, the synthetic camera) writes on a worker would look as if it raced with the
// code that reads it after the join. With OpenCV serial, what is left to check is our own
// threads: the server's io, fusion, admin and DDS threads, the vehicle's link and pose graph.
#include <opencv2/core/utility.hpp>

namespace {

const bool kOpenCvSerial = [] {
  cv::setNumThreads(0);
  return true;
}();

}  // namespace
