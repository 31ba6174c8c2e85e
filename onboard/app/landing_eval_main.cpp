// stereomap-landing-eval: the landing patent's pad on a moving deck, found and measured over a
// simulated descent (30 m -> 2 m, 640x480, image noise and blur), in both pose modes side by
// side against the truth: errors binned by distance, false locks, first lock and speed.
#include <CLI/CLI.hpp>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "common/cli.hpp"
#include "common/statistics.hpp"
#include "onboard/eval/landing_run.hpp"

namespace {

using namespace stereomap;

// NaN when there is nothing to take the median of: the table prints "nan".
double medianOrNan(std::vector<double> values) {
  return common::median(std::move(values)).value_or(std::nan(""));
}

void saveFrame(const std::filesystem::path& dir, const camera::SourceFrame& frame,
               const eval::LandingFrameScore& score, const landing::PadTrack& track) {
  cv::Mat picture;
  cv::cvtColor(frame.left, picture, cv::COLOR_GRAY2BGR);
  if (track.state == landing::TrackState::kTracking) {
    for (int k = 0; k < 8; ++k) {
      cv::circle(picture, track.corners[k], 3, {0, 0, 255}, 1, cv::LINE_AA);
      cv::putText(picture, std::string(1, static_cast<char>('a' + k)),
                  track.corners[k] + cv::Point2d(4, -4), cv::FONT_HERSHEY_SIMPLEX, 0.4,
                  {0, 255, 255}, 1, cv::LINE_AA);
    }
  }
  cv::putText(picture, std::string(landing::toString(track.state)) + ": " + track.reason, {8, 20},
              cv::FONT_HERSHEY_SIMPLEX, 0.5, {0, 255, 0}, 1, cv::LINE_AA);
  char name[64];
  std::snprintf(name, sizeof(name), "deck_%06.2fs_%04.1fm.png", score.t_s, score.distance_m);
  if (!cv::imwrite((dir / name).string(), picture)) {
    std::fprintf(stderr, "cannot write %s\n", (dir / name).c_str());
  }
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "stereomap-landing-eval: the T pad on a moving deck over a simulated descent, default and "
      "patent pose modes against the truth"};
  sim::DeckSourceOptions source_options;
  eval::LandingRunOptions run_options;
  std::string save_dir, csv_path;
  int save_every = 0;
  app.add_option("--seed", source_options.seed, "Scene seed (the deck's texture)")
      ->capture_default_str();
  app.add_option("--every", run_options.every, "Score every n-th frame (10 Hz)")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  app.add_option("--noise", source_options.render.camera.noise_sigma,
                 "Image noise, grey levels (sigma)")
      ->check(CLI::Range(0.0, 50.0))
      ->capture_default_str();
  app.add_option("--blur", source_options.render.camera.blur_sigma, "Image blur, pixels (sigma)")
      ->check(CLI::Range(0.0, 10.0))
      ->capture_default_str();
  std::string camera_preset;
  app.add_option("--camera", camera_preset,
                 "Camera model: clean, typical or poor (stereomap-onboard --help); --noise and "
                 "--blur then set its read noise and defocus (default: typical)")
      ->check(CLI::IsMember({"clean", "typical", "poor"}));
  app.add_option("--supersample", source_options.render.supersample,
                 "Rays per pixel along each axis (anti-aliasing)")
      ->check(CLI::Range(1, 8))
      ->capture_default_str();
  app.add_option("--start", source_options.start_s, "Seconds into the 60 s descent to begin")
      ->check(CLI::Range(0.0, 60.0))
      ->capture_default_str();
  app.add_option("--frames", source_options.max_frames, "Frames to run (0: to the end)")
      ->capture_default_str();
  app.add_option("--csv", csv_path, "Write every scored frame's figures to this CSV file");
  app.add_option("--save-frames", save_dir,
                 "Write every --save-every-th scored frame as a PNG here");
  app.add_option("--save-every", save_every, "With --save-frames: one picture per this many")
      ->check(CLI::Range(1, 100000));
  if (auto exit_code = common::parseCommandLine(app, argc, argv)) return *exit_code;
  if (!camera_preset.empty()) {
    sim::CameraModel& model = source_options.render.camera;
    const double noise = model.noise_sigma, blur = model.blur_sigma;
    model = *sim::CameraModel::preset(camera_preset);
    if (app.count("--noise") > 0) model.noise_sigma = noise;
    if (app.count("--blur") > 0) model.blur_sigma = blur;
  }
  // Both outputs checked before the run (it takes minutes), not after.
  std::FILE* csv = nullptr;
  if (!csv_path.empty() && (csv = std::fopen(csv_path.c_str(), "w")) == nullptr) {
    std::fprintf(stderr, "cannot write %s: %s\n", csv_path.c_str(), std::strerror(errno));
    return 1;
  }
  if (!save_dir.empty()) {
    std::error_code error;
    std::filesystem::create_directories(save_dir, error);
    if (error) {
      std::fprintf(stderr, "cannot create %s: %s\n", save_dir.c_str(), error.message().c_str());
      return 1;
    }
    run_options.on_frame = [&save_dir, count = 0, every = std::max(save_every, 1)](
                               const camera::SourceFrame& frame,
                               const eval::LandingFrameScore& score,
                               const landing::PadTrack& track) mutable {
      if (count++ % every == 0) saveFrame(save_dir, frame, score, track);
    };
  }

  sim::DeckSource source(source_options);
  std::printf("%s, every %d frame(s)\n", source.describe().c_str(), run_options.every);
  const auto scores = eval::runLanding(source, run_options);

  if (csv != nullptr) {
    std::fprintf(
        csv,
        "t_s,distance_m,state,detected,corner_px,default_position_pct,default_attitude_"
        "deg,patent_position_pct,patent_attitude_deg,heave_rate_error,track_ms,default_pose_ms\n");
    for (const auto& s : scores) {
      std::fprintf(csv, "%.2f,%.3f,%s,%d,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f,%.2f,%.2f\n", s.t_s,
                   s.distance_m, landing::toString(s.state), s.detected ? 1 : 0, s.corner_error_px,
                   s.modes[0].published ? s.modes[0].position_pct : NAN,
                   s.modes[0].published ? s.modes[0].attitude_deg : NAN,
                   s.modes[1].published ? s.modes[1].position_pct : NAN,
                   s.modes[1].published ? s.modes[1].attitude_deg : NAN,
                   s.deck_valid ? s.heave_rate_error : NAN, s.track_ms, s.pose_ms[0]);
    }
    if (std::fclose(csv) != 0) {
      std::fprintf(stderr, "cannot write %s: %s\n", csv_path.c_str(), std::strerror(errno));
      return 1;
    }
  }
  // Bins around 5, 10, 20 and 30 m (+-2.5 m).
  const double centres[] = {5, 10, 20, 30};
  const char* names[] = {"default", "patent"};
  std::printf("%-6s %-8s %7s %8s %10s %10s %12s %12s %12s %7s\n", "dist", "mode", "frames",
              "detected", "published", "corner px", "position %", "attitude deg", "p90 pos %",
              "false");
  double at20[2][2] = {{NAN, NAN}, {NAN, NAN}};
  for (const double centre : centres) {
    for (int m = 0; m < 2; ++m) {
      std::vector<double> position, attitude, corners;
      int frames = 0, detected = 0, published = 0, wrong = 0;
      for (const auto& s : scores) {
        if (std::abs(s.distance_m - centre) > 2.5) continue;
        ++frames;
        const bool tracking = s.state == landing::TrackState::kTracking;
        detected += tracking;
        if (tracking) corners.push_back(s.corner_error_px);
        if (!s.modes[m].published) continue;
        ++published;
        position.push_back(s.modes[m].position_pct);
        attitude.push_back(s.modes[m].attitude_deg);
        wrong += s.modes[m].position_pct > 5.0;
      }
      std::vector<double> sorted = position;
      std::sort(sorted.begin(), sorted.end());
      const double p90 = sorted.empty() ? NAN : sorted[sorted.size() * 9 / 10];
      const double pos = medianOrNan(position), att = medianOrNan(attitude);
      if (centre == 20) {
        at20[m][0] = pos;
        at20[m][1] = att;
      }
      std::printf("%4.0f m %-8s %7d %8d %10d %10.3f %12.3f %12.3f %12.3f %7d\n", centre, names[m],
                  frames, detected, published, medianOrNan(corners), pos, att, p90, wrong);
    }
  }
  // First lock: frames from the first one with the whole pad in view to the first TRACKING.
  int first_in_view = -1, first_lock = -1, lost = 0, detections = 0;
  std::vector<double> detect_ms, follow_ms, pose_ms[2], corner_px;
  double heave_squared = 0, deck_attitude_squared = 0;
  int heave_n = 0;
  int false_locks[2] = {0, 0};
  for (size_t i = 0; i < scores.size(); ++i) {
    const auto& s = scores[i];
    const bool tracking = s.state == landing::TrackState::kTracking;
    if (first_in_view < 0 && s.corners_in_view == 8) first_in_view = static_cast<int>(i);
    if (first_lock < 0 && tracking) first_lock = static_cast<int>(i);
    lost += s.state == landing::TrackState::kLost;
    detections += s.detected;
    detect_ms.push_back(s.detect_ms);
    if (tracking && !s.detected) follow_ms.push_back(s.track_ms);
    if (tracking) corner_px.push_back(s.corner_error_px);
    for (int m = 0; m < 2; ++m) {
      if (tracking) pose_ms[m].push_back(s.pose_ms[m]);
      false_locks[m] += s.modes[m].published && s.modes[m].position_pct > 5.0;
    }
    if (s.deck_valid) {
      heave_squared += s.heave_rate_error * s.heave_rate_error;
      deck_attitude_squared += s.deck_attitude_error_deg * s.deck_attitude_error_deg;
      ++heave_n;
    }
  }
  std::printf(
      "first lock: frame %d (pad wholly in view from frame %d); full detections %d, frames LOST "
      "%d; corners %.3f px RMS (median); false locks (> 5 %% of distance): default %d, patent %d "
      "of %zu frames\n",
      first_lock, first_in_view, detections, lost, medianOrNan(corner_px), false_locks[0],
      false_locks[1], scores.size());
  std::printf(
      "deck motion while tracking: heave rate error %.3f m/s RMS, deck attitude %.3f deg "
      "RMS (%d frames)\n",
      heave_n ? std::sqrt(heave_squared / heave_n) : NAN,
      heave_n ? std::sqrt(deck_attitude_squared / heave_n) : NAN, heave_n);
  std::printf(
      "speed on one core (median, ms): tracking %.2f, full detection %.2f, default pose %.2f, "
      "patent pose %.3f\n",
      medianOrNan(follow_ms), medianOrNan(detect_ms), medianOrNan(pose_ms[0]),
      medianOrNan(pose_ms[1]));
  std::printf("landing at 20 m: default %.3f%% / %.3f deg, patent %.3f%% / %.3f deg\n", at20[0][0],
              at20[0][1], at20[1][0], at20[1][1]);
  return 0;
}
