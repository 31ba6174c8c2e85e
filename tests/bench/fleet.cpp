#include "tests/bench/fleet.hpp"

#include <sys/resource.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <memory>
#include <stdexcept>
#include <thread>

#include "common/time.hpp"
#include "server/core/latency.hpp"
#include "server/core/map_server.hpp"
#include "server/store/session_journals.hpp"
#include "tests/bench/bench_support.hpp"
#include "tests/support/server_fixture.hpp"

namespace stereomap::bench {

namespace fs = std::filesystem;
using namespace std::chrono_literals;

namespace {

std::string recordedSession(int k) { return "fleet-rec-" + std::to_string(k); }

// Flies the vehicles side by side into one server; each one's frames are taken late rather
// than skipped on a busy machine (--skip-late off), so its stream is what it sends at 10 Hz.
void recordFlights(const fs::path& store, int count, int frames, int domain) {
  std::printf("recording %d vehicles' streams (%d frames each, typical camera) into %s...\n", count,
              frames, store.c_str());
  std::fflush(stdout);
  fs::create_directories(store);
  testing::ServerProcess server(domain, {}, store.string());
  std::vector<std::unique_ptr<testing::ChildProcess>> vehicles;
  for (int k = 1; k <= count; ++k) {
    std::vector<std::string> argv = {std::string(STEREOMAP_BIN_DIR) + "/stereomap-onboard",
                                     "--source",
                                     "sim",
                                     "--seed",
                                     std::to_string(k),
                                     "--camera",
                                     "typical",
                                     "--frames",
                                     std::to_string(frames),
                                     "--rate",
                                     "10",
                                     "--skip-late",
                                     "off",
                                     "--session",
                                     recordedSession(k),
                                     "--vehicle",
                                     "rec-" + std::to_string(k),
                                     "--spool",
                                     "memory",
                                     "--flush-timeout",
                                     "60",
                                     "--dds-config",
                                     STEREOMAP_DDS_CONFIG,
                                     "--domain",
                                     std::to_string(domain)};
    vehicles.push_back(std::make_unique<testing::ChildProcess>(
        argv, server.logPath() + ".vehicle-" + std::to_string(k)));
  }
  for (int k = 0; k < count; ++k) {
    const auto code = vehicles[k]->waitExit(30min);
    if (!code || *code != 0) {
      throw std::runtime_error("recording vehicle " + std::to_string(k + 1) + " failed: see " +
                               server.logPath() + ".vehicle-" + std::to_string(k + 1));
    }
  }
}

FleetStream readStream(const fs::path& journal) {
  FleetStream stream;
  int64_t first_ns = 0;
  auto add = [&](auto&& message) {
    if (first_ns == 0) first_ns = message.stamp_ns;
    stream.samples.push_back({static_cast<double>(message.stamp_ns - first_ns) * 1e-9,
                              std::forward<decltype(message)>(message)});
  };
  const auto read = store::visitJournal(journal, 0, [&](store::JournalRecord&& record, uint64_t) {
    if (auto* cloud = std::get_if<proto::CloudFrameMsg>(&record)) {
      ++stream.clouds;
      stream.cloud_bytes += cloud->payload.size();
      add(std::move(*cloud));
    } else if (auto* pose = std::get_if<proto::PoseMsg>(&record)) {
      ++stream.poses;
      add(std::move(*pose));
    } else if (auto* event = std::get_if<proto::SessionEventMsg>(&record)) {
      if (event->kind == proto::SessionEventKind::kStarted) add(std::move(*event));
    }
  });
  if (!read || !read->problem.empty() || stream.clouds == 0) {
    throw std::runtime_error("cannot read the recorded stream " + journal.string());
  }
  std::stable_sort(stream.samples.begin(), stream.samples.end(),
                   [](const FleetSample& a, const FleetSample& b) { return a.t_s < b.t_s; });
  // Samples are 0.1 s apart: the lap ends one frame after the last.
  stream.lap_s = stream.samples.back().t_s + 0.1;
  return stream;
}

// One sample due at `due_s` from the start for vehicle `vehicle`.
struct Due {
  double due_s;
  int vehicle;
  const FleetSample* sample;
};

// Every vehicle's samples over `seconds`, split by the thread that hands them over: clouds,
// and the rest (poses, events). Vehicle v plays stream v % K from phase v * 0.618 laps.
void schedule(const std::vector<FleetStream>& streams, int vehicles, double seconds,
              std::vector<Due>& clouds, std::vector<Due>& others) {
  for (int v = 0; v < vehicles; ++v) {
    const FleetStream& stream = streams[v % streams.size()];
    const double phase = stream.lap_s * std::fmod(v * 0.6180339887, 1.0);
    // Its session starts first; then the lap from its phase, wrapping round.
    for (const auto& sample : stream.samples) {
      if (std::holds_alternative<proto::SessionEventMsg>(sample.message)) {
        others.push_back({0.0, v, &sample});
      }
    }
    for (double lap_start = -phase; lap_start < seconds; lap_start += stream.lap_s) {
      for (const auto& sample : stream.samples) {
        if (std::holds_alternative<proto::SessionEventMsg>(sample.message)) continue;
        const double due = lap_start + sample.t_s;
        if (due < 0.001 || due >= seconds) continue;
        (std::holds_alternative<proto::CloudFrameMsg>(sample.message) ? clouds : others)
            .push_back({due, v, &sample});
      }
    }
  }
  auto by_time = [](const Due& a, const Due& b) { return a.due_s < b.due_s; };
  std::stable_sort(clouds.begin(), clouds.end(), by_time);
  std::stable_sort(others.begin(), others.end(), by_time);
}

double cpuSeconds() {
  rusage usage{};
  ::getrusage(RUSAGE_SELF, &usage);
  return static_cast<double>(usage.ru_utime.tv_sec + usage.ru_stime.tv_sec) +
         static_cast<double>(usage.ru_utime.tv_usec + usage.ru_stime.tv_usec) * 1e-6;
}

}  // namespace

std::vector<FleetStream> fleetStreams(const fs::path& dir, int count, int frames, int domain) {
  const fs::path store = dir / "store";
  const fs::path done = dir / ("recorded-" + std::to_string(count) + "x" + std::to_string(frames));
  if (!fs::exists(done)) {
    std::error_code ec;
    fs::remove_all(store, ec);
    recordFlights(store, count, frames, domain);
    std::ofstream(done) << "complete\n";
  }
  std::vector<FleetStream> streams;
  for (int k = 1; k <= count; ++k) {
    streams.push_back(readStream(store / recordedSession(k) / store::kJournalName));
    const auto& s = streams.back();
    std::printf("stream %d: %.1f s, %zu clouds (%.1f/s, %.1f KiB each), %zu poses\n", k, s.lap_s,
                s.clouds, static_cast<double>(s.clouds) / s.lap_s,
                static_cast<double>(s.cloud_bytes) / static_cast<double>(s.clouds) / 1024, s.poses);
  }
  std::fflush(stdout);
  return streams;
}

FleetRun runFleet(const std::vector<FleetStream>& streams, int vehicles, double seconds,
                  const fs::path& store_dir, double rss_before) {
  FleetRun run;
  run.vehicles = vehicles;
  std::vector<Due> clouds, others;
  schedule(streams, vehicles, seconds, clouds, others);

  store::SessionJournals journals(store_dir, 0.1);
  core::MapServer server(
      {.resolution = 0.1, .log = &journals, .snapshots = &journals, .archive = &journals});
  std::atomic<bool> done{false};
  std::atomic<double> rss_peak{rss_before};
  std::thread memory([&] {
    while (!done) {
      rss_peak = std::max(rss_peak.load(), residentMegabytes());
      std::this_thread::sleep_for(250ms);
    }
  });
  std::thread acks([&] {
    while (!done) {
      server.takeAcks();
      std::this_thread::sleep_for(200ms);
    }
  });
  const auto start = Clock::now();
  const double cpu_start = cpuSeconds();
  auto at = [&](double s) {
    return start + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(s));
  };
  // Each vehicle's stream id and seqs are its own: a fresh stream, numbered from 0 per topic.
  std::vector<uint64_t> cloud_seq(vehicles, 0), other_seq(vehicles, 0);
  core::LatencyHistogram late[2];
  auto feed = [&](const std::vector<Due>& due, std::vector<uint64_t>& seqs,
                  core::LatencyHistogram& lateness) {
    for (const Due& d : due) {
      std::this_thread::sleep_until(at(d.due_s));
      lateness.add(std::chrono::duration<double>(Clock::now() - at(d.due_s)).count());
      const std::string id = "fleet-" + std::to_string(d.vehicle);
      std::visit(
          [&](auto message) {
            message.vehicle_id = id;
            message.session_id = id;
            message.stream = static_cast<uint64_t>(d.vehicle) + 1;
            message.seq = seqs[d.vehicle]++;
            message.unacked_from = message.seq;
            message.stamp_ns = common::nowNs();
            if constexpr (std::is_same_v<decltype(message), proto::CloudFrameMsg>) {
              server.ingest(message, core::Origin::kLive, 0, at(d.due_s));
            } else {
              server.ingest(message);
            }
          },
          d.sample->message);
    }
  };
  std::thread cloud_reader([&] { feed(clouds, cloud_seq, late[0]); });
  feed(others, other_seq, late[1]);
  cloud_reader.join();
  run.seconds = std::chrono::duration<double>(Clock::now() - start).count();
  const double cpu = cpuSeconds() - cpu_start;
  for (const auto& session : server.sessions()) session->waitUntilIdle();
  done = true;
  memory.join();
  acks.join();

  core::LatencyHistogram lag;
  for (const auto& session : server.sessions()) {
    const auto status = session->status();
    run.received += status.frames_received;
    run.dropped += status.frames_dropped + status.frames_deferred;
    lag.merge(status.publish_lag);
  }
  late[0].merge(late[1]);
  run.clouds = clouds.size();
  run.poses = others.size();
  run.lag_p50_ms = 1000 * lag.quantile(0.5);
  run.lag_p95_ms = 1000 * lag.quantile(0.95);
  run.lag_max_ms = 1000 * lag.max();
  run.late_p95_ms = 1000 * late[0].quantile(0.95);
  run.cpu_percent = 100 * cpu / run.seconds;
  run.rss_mb = rss_peak - rss_before;
  return run;
}

DdsFleetRun replayOverDds(const std::vector<FleetStream>& streams, int vehicles, double seconds,
                          const proto::DdsOptions& dds, const std::vector<std::string>& vehicle_ids,
                          const std::vector<std::string>& identities, int only,
                          std::optional<std::chrono::system_clock::time_point> start_at) {
  DdsFleetRun run;
  struct Vehicle {
    std::shared_ptr<proto::Participant> participant;
    std::unique_ptr<proto::Writer<proto::PoseMsg>> poses;
    std::unique_ptr<proto::Writer<proto::CloudFrameMsg>> clouds;
    std::unique_ptr<proto::Writer<proto::SessionEventMsg>> events;
  };
  const auto joining = Clock::now();
  std::vector<Vehicle> fleet(static_cast<size_t>(vehicles));
  for (int v = 0; v < vehicles; ++v) {
    if (only >= 0 && v != only) continue;
    auto& vehicle = fleet[static_cast<size_t>(v)];
    proto::DdsOptions options = dds;
    if (!identities.empty()) options.security_dir = identities[static_cast<size_t>(v)];
    auto participant = proto::Participant::create(options);
    if (!participant) {
      run.error = participant.error().message;
      return run;
    }
    vehicle.participant = std::move(participant).value();
    const std::vector<std::string> partition = {
        proto::vehiclePartition("fleet-" + std::to_string(v), vehicle_ids[static_cast<size_t>(v)])};
    auto poses = proto::Writer<proto::PoseMsg>::create(vehicle.participant, partition);
    auto clouds = proto::Writer<proto::CloudFrameMsg>::create(vehicle.participant, partition);
    auto events = proto::Writer<proto::SessionEventMsg>::create(vehicle.participant, partition);
    if (!poses || !clouds || !events) {
      run.error = "cannot create vehicle " + std::to_string(v) + "'s writers";
      return run;
    }
    vehicle.poses = std::move(poses).value();
    vehicle.clouds = std::move(clouds).value();
    vehicle.events = std::move(events).value();
  }
  for (auto& vehicle : fleet) {
    if (!vehicle.participant) continue;
    if (!vehicle.poses->waitForReaders(1, 120s) || !vehicle.clouds->waitForReaders(1, 120s) ||
        !vehicle.events->waitForReaders(1, 120s)) {
      run.error = "a vehicle's writers never matched the server";
      return run;
    }
  }
  run.join_s = std::chrono::duration<double>(Clock::now() - joining).count();

  std::vector<Due> clouds, others;
  schedule(streams, vehicles, seconds, clouds, others);
  if (only >= 0) {
    auto mine = [only](const Due& d) { return d.vehicle != only; };
    clouds.erase(std::remove_if(clouds.begin(), clouds.end(), mine), clouds.end());
    others.erase(std::remove_if(others.begin(), others.end(), mine), others.end());
  }
  if (start_at) std::this_thread::sleep_until(*start_at);
  const auto start = Clock::now();
  auto at = [&](double s) {
    return start + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(s));
  };
  std::vector<uint64_t> cloud_seq(static_cast<size_t>(vehicles), 0);
  std::vector<uint64_t> other_seq(static_cast<size_t>(vehicles), 0);
  core::LatencyHistogram late[2];
  auto feed = [&](const std::vector<Due>& due, std::vector<uint64_t>& seqs,
                  core::LatencyHistogram& lateness) {
    for (const Due& d : due) {
      std::this_thread::sleep_until(at(d.due_s));
      lateness.add(std::chrono::duration<double>(Clock::now() - at(d.due_s)).count());
      auto& vehicle = fleet[static_cast<size_t>(d.vehicle)];
      std::visit(
          [&](auto message) {
            message.vehicle_id = vehicle_ids[static_cast<size_t>(d.vehicle)];
            message.session_id = "fleet-" + std::to_string(d.vehicle);
            message.stream = static_cast<uint64_t>(d.vehicle) + 1;
            message.seq = seqs[static_cast<size_t>(d.vehicle)]++;
            message.unacked_from = message.seq;
            message.stamp_ns = common::nowNs();
            using Message = decltype(message);
            if constexpr (std::is_same_v<Message, proto::CloudFrameMsg>) {
              (void)vehicle.clouds->write(message);
            } else if constexpr (std::is_same_v<Message, proto::PoseMsg>) {
              (void)vehicle.poses->write(message);
            } else {
              (void)vehicle.events->write(message);
            }
          },
          d.sample->message);
    }
  };
  std::thread cloud_writer([&] { feed(clouds, cloud_seq, late[0]); });
  feed(others, other_seq, late[1]);
  cloud_writer.join();
  run.seconds = std::chrono::duration<double>(Clock::now() - start).count();
  for (auto& vehicle : fleet) {
    if (vehicle.clouds) vehicle.clouds->waitForAcks(10s);
  }
  late[0].merge(late[1]);
  run.clouds = clouds.size();
  run.poses = others.size();
  run.late_p95_ms = 1000 * late[0].quantile(0.95);
  return run;
}

}  // namespace stereomap::bench
