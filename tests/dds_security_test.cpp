// DDS Security (issue 55) tried from outside with real processes: a deployment made by
// stereomap-certs, a server and vehicles with --security, and an attacker on the same domain
// (stereomap-dds-probe, our vehicle binary without certificates, ddsperf). Every attack is
// refused and nothing stored is touched; each check has its open twin where it matters, so the
// test shows the attack would work without security.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>

#include "tests/support/secure_deployment.hpp"
#include "tests/support/server_fixture.hpp"
#include "tests/support/stream_count.hpp"

namespace stereomap::testing {
namespace {

using namespace std::chrono_literals;
namespace fs = std::filesystem;

// 122-129: this file, a domain (and its open twin's) per test, as ctest runs them side by side
// (server_fixture.hpp keeps the list).
constexpr int kHeardDomain = 122;
constexpr int kOpenHeardDomain = 123;
constexpr int kAsAnotherDomain = 124;
constexpr int kAckDomain = 125;
constexpr int kOpenAckDomain = 126;
constexpr int kRevokedDomain = 127;
constexpr int kWireDomain = 128;
constexpr int kOpenWireDomain = 129;

const std::string kBin = STEREOMAP_BIN_DIR;

const Deployment& deployment() {
  static const Deployment made = makeDeployment({"v1", "v2"});
  return made;
}

bool has(const std::vector<std::string>& ids, const std::string& id) {
  return std::find(ids.begin(), ids.end(), id) != ids.end();
}

class DdsSecurity : public ::testing::Test {
 protected:
  void SetUp() override { ASSERT_TRUE(deployment().ok) << deployment().log; }
};

// The certified vehicle is heard and acknowledged; the same binary without certificates, and
// an uncertified reader of every partition, get nothing: no session, no acknowledgement, no
// sample.
TEST_F(DdsSecurity, OnlyAuthenticatedParticipantsAreHeardOrServed) {
  ServerProcess server(kHeardDomain, {"--security", deployment().server()});
  ChildProcess listener(
      {kBin + "/stereomap-dds-probe", "read", "--topic", "pose", "--partition", "sm/*", "--seconds",
       "12", "--domain", std::to_string(kHeardDomain), "--dds-config", STEREOMAP_DDS_CONFIG},
      server.logPath() + ".listener");
  // ddsperf without certificates publishing as fast as the loopback takes while v1 flies.
  ChildProcess flood(
      {"/bin/sh", "-c",
       "CYCLONEDDS_URI=file://" + std::string(STEREOMAP_DDS_CONFIG) + " exec ddsperf -i " +
           std::to_string(kHeardDomain) + " -D 10 pub 500Hz size 4k"},
      server.logPath() + ".ddsperf");
  const auto secured = fly(kHeardDomain, "sec-ok", "v1", deployment().vehicle("v1"));
  EXPECT_EQ(secured.exit_code, 0) << secured.log;
  EXPECT_EQ(unacknowledged(secured.log), 0) << secured.log;
  EXPECT_EQ(flood.waitExit(scaledTimeout(30s)).value_or(-1), 0)
      << readText(server.logPath() + ".ddsperf");

  ASSERT_EQ(listener.waitExit(scaledTimeout(60s)).value_or(-1), 0);
  const std::string heard = readText(server.logPath() + ".listener");
  EXPECT_NE(heard.find("read: read 0, matched 0"), std::string::npos) << heard;

  const auto open = fly(kHeardDomain, "sec-open", "v1", "");
  EXPECT_EQ(open.exit_code, 0) << open.log;
  EXPECT_GT(unacknowledged(open.log), 0) << "nobody acknowledged the uncertified vehicle";

  const auto ids = sessionIds(server);
  EXPECT_EQ(ids, std::vector<std::string>{"sec-ok"}) << "an uncertified vehicle made a session";
  EXPECT_EQ(server.get("/metrics").body.find("stereomap_samples_rejected_total{"),
            std::string::npos)
      << "nothing uncertified even reached the server's checks";
  // The open twin: the same listener on an open deployment hears the vehicle.
  ServerProcess open_server(kOpenHeardDomain);
  ChildProcess open_listener(
      {kBin + "/stereomap-dds-probe", "read", "--topic", "pose", "--partition", "sm/*", "--seconds",
       "10", "--domain", std::to_string(kOpenHeardDomain), "--dds-config", STEREOMAP_DDS_CONFIG},
      server.logPath() + ".open-listener");
  EXPECT_EQ(fly(kOpenHeardDomain, "open-ok", "v1", "").exit_code, 0);
  ASSERT_EQ(open_listener.waitExit(scaledTimeout(60s)).value_or(-1), 0);
  EXPECT_EQ(readText(server.logPath() + ".open-listener").find("read: read 0"), std::string::npos);
}

// Vehicle v1 cannot write as v2: not in v2's partition (its own permissions refuse the writer),
// nor as v2 in its own partition (the server refuses the samples, counts them and names v1's
// certificate); and it cannot read v2's acknowledgements.
TEST_F(DdsSecurity, AVehicleCertifiedAsOneIdCannotSendAsAnother) {
  ServerProcess server(kAsAnotherDomain, {"--security", deployment().server()});
  const auto as_v2 = fly(kAsAnotherDomain, "sec-as", "v2", deployment().vehicle("v1"), 5);
  EXPECT_NE(as_v2.exit_code, 0);
  EXPECT_NE(as_v2.log.find("Not Allowed By Security"), std::string::npos) << as_v2.log;

  const std::string v1 = deployment().vehicle("v1");
  EXPECT_NE(
      probe({"write", "--partition", "sm/sec-as/v/v2", "--vehicle", "v2", "--session", "sec-as"},
            kAsAnotherDomain, v1)
          .find("write: refused"),
      std::string::npos);
  const std::string wrote = probe({"write", "--partition", "sm/sec-as/v/v1", "--vehicle", "v2",
                                   "--session", "sec-as", "--count", "10"},
                                  kAsAnotherDomain, v1);
  EXPECT_NE(wrote.find("write: wrote 10, matched 1"), std::string::npos) << wrote;
  EXPECT_NE(probe({"read", "--topic", "ack", "--partition", "sm/sec-as/v/v2", "--seconds", "1"},
                  kAsAnotherDomain, v1)
                .find("read: refused"),
            std::string::npos);

  ASSERT_TRUE(waitUntil(10s, [&] {
    const std::string metrics = server.get("/metrics").body;
    return seriesValue(metrics,
                       "stereomap_samples_rejected_total{topic=\"Pose\",reason=\"identity\"}") >=
           10;
  })) << server.get("/metrics").body;
  EXPECT_NE(server.log().find("CN=v1"), std::string::npos) << server.log();
  EXPECT_FALSE(has(sessionIds(server), "sec-as"));
}

// Only a server may acknowledge: a vehicle's identity cannot make an Ack writer, and a writer
// without certificates never matches a certified vehicle's reader (in the open it does).
TEST_F(DdsSecurity, AcknowledgementsAreForgedByNobody) {
  const auto forge = [&](int domain, const std::string& identity) {
    return probe({"write", "--topic", "ack", "--partition", "sm/sec-ack/v/v1", "--vehicle", "v1",
                  "--session", "sec-ack", "--match-wait", "8", "--count", "30"},
                 domain, identity);
  };
  EXPECT_NE(forge(kAckDomain, deployment().vehicle("v2")).find("write: refused"),
            std::string::npos);
  for (const auto& [domain, identity, matched] :
       {std::tuple{kAckDomain, deployment().vehicle("v1"), "matched 0"},
        std::tuple{kOpenAckDomain, std::string(), "matched 1"}}) {
    const std::string log = makeTempDir("stereomap-ack") + "/onboard.log";
    std::vector<std::string> extra = {"--vehicle", "v1", "--rate", "5"};
    if (!identity.empty()) extra.insert(extra.end(), {"--security", identity});
    ChildProcess vehicle(onboardArgs(domain, "sec-ack", 60, extra), log);
    const std::string forged = forge(domain, "");
    EXPECT_NE(forged.find(matched), std::string::npos) << "domain " << domain << ": " << forged;
    vehicle.stop();
  }
}

// An expired certificate does not even make a participant; a revoked one (the server's CRL)
// is never heard.
TEST_F(DdsSecurity, ExpiredAndRevokedCertificatesAreRefused) {
  ServerProcess server(kRevokedDomain, {"--security", deployment().server()});
  const auto old = fly(kRevokedDomain, "sec-old", "old", deployment().vehicle("old"), 5);
  EXPECT_NE(old.exit_code, 0) << old.log;
  EXPECT_NE(old.log.find("certificate (" + deployment().vehicle("old") + "/identity.pem) ran out"),
            std::string::npos)
      << old.log;
  const auto lost = fly(kRevokedDomain, "sec-lost", "lost", deployment().vehicle("lost"));
  EXPECT_GT(unacknowledged(lost.log), 0) << lost.log;
  const auto ids = sessionIds(server);
  EXPECT_FALSE(has(ids, "sec-old"));
  EXPECT_FALSE(has(ids, "sec-lost"));
  // The same server still hears a vehicle in good standing.
  EXPECT_EQ(unacknowledged(fly(kRevokedDomain, "sec-good", "v2", deployment().vehicle("v2")).log),
            0);
  EXPECT_TRUE(has(sessionIds(server), "sec-good"));
}

// A capture of the loopback while a secured and an open vehicle fly: the open one's session id
// (in every sample) is there in clear, the secured one's nowhere.
TEST_F(DdsSecurity, TheWireShowsNoPlaintextOfASecuredFlight) {
  const auto found = runTool({"/bin/sh", "-c", "command -v tcpdump"});
  if (found.exit_code != 0) {
    GTEST_SKIP() << "tcpdump is not installed (scripts/install-deps installs it)";
  }
  const std::string tcpdump = found.output.substr(0, found.output.find('\n'));
  const std::string dir = makeTempDir("stereomap-capture");
  ChildProcess capture({tcpdump, "-i", "lo", "-U", "-w", dir + "/lo.pcap", "udp"},
                       dir + "/tcpdump.log");
  ASSERT_TRUE(waitUntil(10s, [&] { return fs::exists(dir + "/lo.pcap"); }));
  std::this_thread::sleep_for(500ms);
  {
    ServerProcess secured(kWireDomain, {"--security", deployment().server()});
    ServerProcess open(kOpenWireDomain);
    EXPECT_EQ(fly(kWireDomain, "secret-flight-4711", "v1", deployment().vehicle("v1")).exit_code,
              0);
    EXPECT_EQ(fly(kOpenWireDomain, "open-flight-4711", "v1", "").exit_code, 0);
    EXPECT_TRUE(has(sessionIds(secured), "secret-flight-4711"));
  }
  capture.stop();
  const std::string wire = readText(dir + "/lo.pcap");
  EXPECT_NE(wire.find("open-flight-4711"), std::string::npos) << "the capture saw nothing";
  EXPECT_EQ(wire.find("secret-flight-4711"), std::string::npos);
  fs::remove_all(dir);
}

}  // namespace
}  // namespace stereomap::testing
