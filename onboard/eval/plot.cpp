#include "onboard/eval/plot.hpp"

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cstdio>
#include <tuple>

namespace stereomap::eval {

namespace {

const cv::Scalar kReference(150, 150, 150), kEstimate(200, 90, 30), kAxis(150, 150, 150);  // BGR

void label(cv::Mat& image, const std::string& text, cv::Point at, double size = 0.5) {
  cv::putText(image, text, at, cv::FONT_HERSHEY_SIMPLEX, size, cv::Scalar(20, 20, 20), 1,
              cv::LINE_AA);
}

std::string metres(double value) {
  char text[32];
  std::snprintf(text, sizeof(text), "%.3g m", value);
  return text;
}

}  // namespace

std::string plotPng(const common::Trajectory& ref, const common::Trajectory& est,
                    const std::vector<double>& errors, const std::string& title, bool frames) {
  cv::Mat image(600, 1400, CV_8UC3, cv::Scalar(255, 255, 255));
  label(image, title, {20, 30}, 0.6);
  if (ref.empty()) {
    std::vector<uchar> png;
    cv::imencode(".png", image, png);
    return {png.begin(), png.end()};
  }
  // Top view: the two axes with the largest spread of the reference.
  common::Vec3 lo = ref[0].pose.translation, hi = lo;
  for (const auto* trajectory : {&ref, &est}) {
    for (const auto& p : *trajectory) {
      lo = lo.cwiseMin(p.pose.translation);
      hi = hi.cwiseMax(p.pose.translation);
    }
  }
  int a = 0, b = 1;
  const common::Vec3 spread = hi - lo;
  if (spread.z() > spread.x() && spread.x() <= spread.y()) a = 2;
  if (spread.z() > spread.y() && spread.y() < spread.x()) b = 2;
  if (a == b) b = a == 0 ? 1 : 0;
  const cv::Rect view(60, 60, 600, 480);
  const double extent = std::max({spread[a], spread[b], 1e-6});
  const double scale = std::min(view.width, view.height) / extent;
  auto toPixel = [&](const common::Vec3& p) {
    return cv::Point(view.x + static_cast<int>((p[a] - lo[a]) * scale),
                     view.y + view.height - static_cast<int>((p[b] - lo[b]) * scale));
  };
  cv::rectangle(image, view, kAxis);
  for (const auto& [trajectory, colour, width] :
       {std::tuple{&ref, kReference, 4}, std::tuple{&est, kEstimate, 1}}) {
    std::vector<cv::Point> line;
    for (const auto& p : *trajectory) line.push_back(toPixel(p.pose.translation));
    cv::polylines(image, line, false, colour, width, cv::LINE_AA);
  }
  const char* axes = "xyz";
  label(image,
        std::string("top view: ") + axes[a] + " right, " + axes[b] + " up; " + metres(extent) +
            " across; grey reference, blue estimate (aligned)",
        {60, 565}, 0.45);

  // Error over time.
  const cv::Rect plot(760, 60, 600, 480);
  cv::rectangle(image, plot, kAxis);
  const double t0 = ref.front().t, t1 = std::max(ref.back().t, t0 + 1e-9);
  const double top = std::max(*std::max_element(errors.begin(), errors.end()), 1e-9);
  std::vector<cv::Point> curve;
  for (size_t i = 0; i < errors.size() && i < ref.size(); ++i) {
    curve.emplace_back(plot.x + static_cast<int>((ref[i].t - t0) / (t1 - t0) * plot.width),
                       plot.y + plot.height - static_cast<int>(errors[i] / top * plot.height));
  }
  cv::polylines(image, curve, false, kEstimate, 1, cv::LINE_AA);
  label(image, "position error over time (0 to " + metres(top) + ")", {760, 565}, 0.45);
  char span[64];
  std::snprintf(span, sizeof(span), frames ? "%.0f frames" : "%.1f s", t1 - t0);
  label(image, span, {plot.x + plot.width - 90, plot.y + plot.height + 20}, 0.45);
  std::vector<uchar> png;
  cv::imencode(".png", image, png);
  return {png.begin(), png.end()};
}

}  // namespace stereomap::eval
