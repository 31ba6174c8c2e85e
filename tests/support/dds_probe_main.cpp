// stereomap-dds-probe: what an attacker on the DDS domain can do, as its own process, for the
// security tests and stereomap-bench-security. It writes poses or acknowledgements as anyone
// into any partition, or reads a topic in any partition, with or without an identity, and
// says what happened in one line:
//   write: refused: <why>            (the participant or writer could not be made)
//   write: wrote N, matched M         (M readers ever matched)
//   read: read N, matched M
// Exit 0 when it ran, 3 when DDS Security refused it, 2 on bad usage.
#include <CLI/CLI.hpp>

#include <chrono>
#include <cstdio>
#include <thread>

#include "common/time.hpp"
#include "proto/dds.hpp"
#include "proto/dds_cli.hpp"

namespace {

using namespace stereomap;
using namespace std::chrono_literals;

struct Flags {
  proto::DdsOptions dds;
  std::string topic = "pose";
  std::string partition;
  std::string vehicle = "v1";
  std::string session = "s";
  uint64_t stream = 1;
  int count = 20;
  double seconds = 5;
  double match_wait = 3;
};

template <typename T>
int refused(const char* what, const common::Error& error) {
  std::printf("%s: refused: %s\n", what, error.message.c_str());
  return 3;
}

template <typename T>
T sample(const Flags& f, int i) {
  T message;
  message.vehicle_id = f.vehicle;
  message.session_id = f.session;
  message.stream = f.stream;
  message.stamp_ns = common::nowNs();
  if constexpr (std::is_same_v<T, proto::PoseMsg>) {
    message.seq = static_cast<uint64_t>(i + 1);
    message.position = {0.1 * i, 0, 1};
  } else {
    // Everything acknowledged: a vehicle that believed it would drop its spool.
    message.poses = message.clouds = message.events = message.corrections = 1'000'000;
  }
  return message;
}

template <typename T>
int write(const Flags& f, const std::shared_ptr<proto::Participant>& participant) {
  auto writer = proto::Writer<T>::create(participant, {f.partition});
  if (!writer) return refused<T>("write", writer.error());
  (*writer)->waitForReaders(1, std::chrono::milliseconds(static_cast<int64_t>(f.match_wait * 1e3)));
  int matched = (*writer)->matchedReaders();
  for (int i = 0; i < f.count; ++i) {
    (void)(*writer)->write(sample<T>(f, i));
    matched = std::max(matched, (*writer)->matchedReaders());
    std::this_thread::sleep_for(100ms);
  }
  (*writer)->waitForAcks(2s);
  std::printf("write: wrote %d, matched %d\n", f.count, matched);
  return 0;
}

template <typename T>
int read(const Flags& f, const std::shared_ptr<proto::Participant>& participant) {
  auto reader = proto::Reader<T>::create(participant, {f.partition});
  if (!reader) return refused<T>("read", reader.error());
  std::vector<T> taken;
  int matched = 0;
  const auto end = std::chrono::steady_clock::now() +
                   std::chrono::milliseconds(static_cast<int64_t>(f.seconds * 1e3));
  while (std::chrono::steady_clock::now() < end) {
    (*reader)->take(taken, 100ms);
    matched = std::max(matched, (*reader)->matchedWriters());
  }
  std::printf("read: read %zu, matched %d\n", taken.size(), matched);
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"stereomap-dds-probe: write or read stereomap's topics as anyone (security tests)"};
  Flags f;
  std::string mode = "write";
  app.add_option("mode", mode, "write or read")->check(CLI::IsMember({"write", "read"}));
  app.add_option("--topic", f.topic, "pose or ack")->check(CLI::IsMember({"pose", "ack"}));
  app.add_option("--partition", f.partition, "DDS partition (e.g. sm/S/v/V, sm/*)")->required();
  app.add_option("--vehicle", f.vehicle, "vehicle_id written in the samples");
  app.add_option("--session", f.session, "session_id written in the samples");
  app.add_option("--stream", f.stream, "stream written in the samples");
  app.add_option("--count", f.count, "samples to write, 10 a second")->check(CLI::Range(1, 100000));
  app.add_option("--seconds", f.seconds, "how long to read")->check(CLI::Range(0.1, 3600.0));
  app.add_option("--match-wait", f.match_wait, "seconds to wait for a reader before writing")
      ->check(CLI::Range(0.0, 60.0));
  proto::addDdsFlags(app, f.dds);
  CLI11_PARSE(app, argc, argv);
  auto participant = proto::Participant::create(f.dds);
  if (!participant) return refused<int>(mode.c_str(), participant.error());
  if (mode == "write") {
    return f.topic == "pose" ? write<proto::PoseMsg>(f, *participant)
                             : write<proto::AckMsg>(f, *participant);
  }
  return f.topic == "pose" ? read<proto::PoseMsg>(f, *participant)
                           : read<proto::AckMsg>(f, *participant);
}
