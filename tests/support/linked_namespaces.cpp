#include "tests/support/linked_namespaces.hpp"

#include <fcntl.h>
#include <sched.h>
#include <unistd.h>

#include <cstdlib>

#include <filesystem>
#include <regex>
#include <sstream>
#include <stdexcept>
#include <vector>

#include "tests/support/process.hpp"

namespace stereomap::testing {

namespace {

constexpr const char* kIp = "/usr/sbin/ip";
constexpr const char* kTc = "/usr/sbin/tc";
constexpr const char* kNft = "/usr/sbin/nft";

ToolRun run(const std::vector<std::string>& argv) {
  return runTool(argv, std::chrono::seconds(20));
}

void mustRun(const std::vector<std::string>& argv) {
  const auto result = run(argv);
  if (result.exit_code != 0) {
    std::string command;
    for (const auto& a : argv) command += a + " ";
    throw std::runtime_error("'" + command + "' failed: " + result.output);
  }
}

std::vector<std::string> inNamespace(const std::string& ns, std::vector<std::string> argv) {
  argv.insert(argv.begin(), {kIp, "netns", "exec", ns});
  return argv;
}

}  // namespace

std::optional<std::string> LinkedNamespaces::unavailable() {
  if (::geteuid() != 0) return "network namespaces need root";
  for (const char* tool : {kIp, kTc, kNft}) {
    if (::access(tool, X_OK) != 0) {
      return std::string(tool) + " is missing (scripts/install-deps installs it)";
    }
  }
  const std::string probe = "smprobe" + std::to_string(::getpid());
  if (run({kIp, "netns", "add", probe}).exit_code != 0) return "ip netns add fails here";
  run({kIp, "netns", "del", probe});
  return std::nullopt;
}

LinkedNamespaces::LinkedNamespaces(const std::string& tag, int subnet) {
  const std::string id = tag.substr(0, 4) + std::to_string(::getpid());
  const std::string net = "10.213." + std::to_string(subnet % 256) + ".";
  server_ = {"sms-" + id, "vs-" + id, net + "1", net + "2", ""};
  vehicle_ = {"smv-" + id, "vv-" + id, net + "2", net + "1", ""};
  sweepStale();
  std::vector<std::string> made;
  try {
    for (const Side* side : {&server_, &vehicle_}) {
      mustRun({kIp, "netns", "add", side->ns});
      made.push_back(side->ns);
    }
    mustRun({kIp, "link", "add", server_.dev, "type", "veth", "peer", "name", vehicle_.dev});
    for (Side* side : {&server_, &vehicle_}) {
      mustRun({kIp, "link", "set", side->dev, "netns", side->ns});
      mustRun({kIp, "-n", side->ns, "addr", "add", side->address + "/30", "dev", side->dev});
      mustRun({kIp, "-n", side->ns, "link", "set", side->dev, "up"});
      mustRun({kIp, "-n", side->ns, "link", "set", "lo", "up"});
    }
  } catch (...) {
    // The veth pair starts in this namespace: gone with its namespace once moved, else here.
    run({kIp, "link", "del", server_.dev});
    for (const auto& ns : made) run({kIp, "netns", "del", ns});
    throw;
  }
}

void LinkedNamespaces::sweepStale() {
  // Namespaces of an earlier run that was killed (a test timeout): named sms-/smv- with its
  // process id last; removed when that process is gone.
  const auto list = run({kIp, "netns", "list"});
  std::istringstream lines(list.output);
  std::string name;
  while (lines >> name) {
    if (name.rfind("sms-", 0) != 0 && name.rfind("smv-", 0) != 0) continue;
    const size_t digits = name.find_last_not_of("0123456789") + 1;
    if (digits >= name.size()) continue;
    const std::string pid = name.substr(digits);
    if (!std::filesystem::exists("/proc/" + pid)) run({kIp, "netns", "del", name});
    std::getline(lines, name);  // the rest of the line ("(id: N)")
  }
}

LinkedNamespaces::~LinkedNamespaces() {
  relay_.reset();
  // Deleting a namespace deletes the veth end in it, and with it the other end.
  for (const Side* side : {&server_, &vehicle_}) run({kIp, "netns", "del", side->ns});
}

void LinkedNamespaces::shape(const LinkShape& shape) {
  for (const Side* side : {&server_, &vehicle_}) {
    if (!shape.rate.empty()) {
      mustRun(inNamespace(side->ns, {kTc, "qdisc", "replace", "dev", side->dev, "root", "tbf",
                                     "rate", shape.rate, "burst", "32kbit", "latency", "400ms"}));
    }
    if (shape.loss_percent > 0) {
      mustRun(inNamespace(side->ns, {kNft, "add", "table", "inet", "smloss"}));
      mustRun(inNamespace(side->ns, {kNft, "add", "chain", "inet", "smloss", "out",
                                     "{ type filter hook output priority 0 ; }"}));
      mustRun(inNamespace(side->ns, {kNft, "add", "rule", "inet", "smloss", "out", "oifname",
                                     side->dev, "numgen", "random", "mod", "100", "<",
                                     std::to_string(shape.loss_percent), "counter", "drop"}));
    }
  }
}

void LinkedNamespaces::delayToServer(std::chrono::milliseconds delay, int dds_domain) {
  // An address in the vehicle's namespace (its loopback device), outside the veth's /30.
  const std::string relay = server_.address.substr(0, server_.address.rfind('.') + 1) + "5";
  mustRun({kIp, "-n", vehicle_.ns, "addr", "add", relay + "/32", "dev", "lo"});
  std::vector<int> ports;
  const int base = 7400 + 250 * dds_domain;  // Cyclone's port mapping: unicast discovery
  for (int index = 0; index < 4; ++index) {  // base + 10 + 2i, unicast data base + 11 + 2i
    ports.push_back(base + 10 + 2 * index);
    ports.push_back(base + 11 + 2 * index);
  }
  relay_ = std::make_unique<UdpDelayRelay>(vehicle_.ns, relay, server_.address, ports, delay);
  server_.dds_external = relay;
  vehicle_.dds_peer = relay;
}

LinkedNamespaces::Entered::Entered(const Side& side) {
  previous_ = ::open("/proc/thread-self/ns/net", O_RDONLY | O_CLOEXEC);
  const int target = ::open(("/run/netns/" + side.ns).c_str(), O_RDONLY | O_CLOEXEC);
  const bool ok = previous_ >= 0 && target >= 0 && ::setns(target, CLONE_NEWNET) == 0;
  if (target >= 0) ::close(target);
  if (!ok) {
    if (previous_ >= 0) ::close(previous_);
    throw std::runtime_error("cannot enter network namespace " + side.ns);
  }
  ::setenv("STEREOMAP_DDS_INTERFACE", side.address.c_str(), 1);
  ::setenv("STEREOMAP_DDS_PEER", side.dds_peer.c_str(), 1);
  if (side.dds_external.empty()) {
    ::unsetenv("STEREOMAP_DDS_EXTERNAL_ADDRESS");
  } else {
    ::setenv("STEREOMAP_DDS_EXTERNAL_ADDRESS", side.dds_external.c_str(), 1);
  }
}

LinkedNamespaces::Entered::~Entered() {
  ::setns(previous_, CLONE_NEWNET);
  ::close(previous_);
  for (const char* name :
       {"STEREOMAP_DDS_INTERFACE", "STEREOMAP_DDS_PEER", "STEREOMAP_DDS_EXTERNAL_ADDRESS"}) {
    ::unsetenv(name);
  }
}

LinkedNamespaces::QueueStats LinkedNamespaces::queue(const Side& side) const {
  const auto result = run(inNamespace(side.ns, {kTc, "-s", "qdisc", "show", "dev", side.dev}));
  QueueStats stats;
  std::smatch match;
  if (std::regex_search(result.output, match, std::regex(R"(dropped (\d+))"))) {
    stats.dropped = std::stol(match[1]);
  }
  if (std::regex_search(result.output, match, std::regex(R"(backlog (\d+)b)"))) {
    stats.backlog_bytes = std::stol(match[1]);
  }
  const auto loss = run(inNamespace(side.ns, {kNft, "list", "table", "inet", "smloss"}));
  if (std::regex_search(loss.output, match, std::regex(R"(counter packets (\d+))"))) {
    stats.lost = std::stol(match[1]);
  }
  return stats;
}

}  // namespace stereomap::testing
