#include "onboard/camera/cv_pose.hpp"

namespace stereomap::camera {

common::Rigid3 rigidFromRvecTvec(const cv::Mat& rvec, const cv::Mat& tvec) {
  cv::Mat r, t;
  rvec.convertTo(r, CV_64F);
  tvec.convertTo(t, CV_64F);
  const Eigen::Vector3d v(r.at<double>(0), r.at<double>(1), r.at<double>(2));
  const double angle = v.norm();
  const common::Quat q =
      angle < 1e-12 ? common::Quat::Identity() : common::Quat(Eigen::AngleAxisd(angle, v / angle));
  return {q, common::Vec3(t.at<double>(0), t.at<double>(1), t.at<double>(2))};
}

}  // namespace stereomap::camera
