#include "tests/support/secure_deployment.hpp"

#include <nlohmann/json.hpp>

#include <filesystem>
#include <regex>

#include "tests/support/stream_count.hpp"

namespace stereomap::testing {

namespace fs = std::filesystem;
using namespace std::chrono_literals;

namespace {
const std::string kBin = STEREOMAP_BIN_DIR;
}

Deployment makeDeployment(const std::vector<std::string>& vehicles) {
  Deployment d;
  d.dir = makeTempDir("stereomap-deployment");
  fs::remove(d.dir);  // init makes it
  std::vector<std::vector<std::string>> steps = {{"init", d.dir}, {"server", d.dir, "s1"}};
  for (const auto& id : vehicles) steps.push_back({"vehicle", d.dir, id});
  steps.push_back({"vehicle", d.dir, "old", "--not-before", "20200101000000Z", "--not-after",
                   "20200201000000Z"});
  steps.push_back({"vehicle", d.dir, "lost"});
  steps.push_back({"revoke", d.dir, "vehicle", "lost"});
  d.ok = true;
  for (auto step : steps) {
    step.insert(step.begin(), kBin + "/stereomap-certs");
    const auto run = runTool(step);
    d.log += run.output;
    d.ok = d.ok && run.exit_code == 0;
  }
  return d;
}

std::string probe(const std::vector<std::string>& args, int domain, const std::string& identity) {
  std::vector<std::string> argv = {kBin + "/stereomap-dds-probe", "--domain",
                                   std::to_string(domain), "--dds-config", STEREOMAP_DDS_CONFIG};
  if (!identity.empty()) argv.insert(argv.end(), {"--security", identity});
  argv.insert(argv.end(), args.begin(), args.end());
  return runTool(argv, 60s).output;
}

Flight fly(int domain, const std::string& session, const std::string& vehicle,
           const std::string& identity, int frames, const std::vector<std::string>& extra) {
  std::vector<std::string> flags = {"--vehicle", vehicle};
  if (!identity.empty()) flags.insert(flags.end(), {"--security", identity});
  flags.insert(flags.end(), extra.begin(), extra.end());
  const std::string log = makeTempDir("stereomap-flight") + "/onboard.log";
  ChildProcess onboard(onboardArgs(domain, session, frames, flags), log);
  Flight flight;
  flight.exit_code = onboard.waitExit(scaledTimeout(120s)).value_or(-1);
  flight.log = readText(log);
  fs::remove_all(fs::path(log).parent_path());
  return flight;
}

int unacknowledged(const std::string& log) {
  std::smatch match;
  static const std::regex pattern(R"re((\d+) still unacknowledged)re");
  return std::regex_search(log, match, pattern) ? std::stoi(match[1]) : -1;
}

std::vector<std::string> sessionIds(const ServerProcess& server) {
  std::vector<std::string> ids;
  const auto reply = server.get("/api/sessions");
  if (reply.status != 200) return ids;
  for (const auto& session : nlohmann::json::parse(reply.body)) ids.push_back(session["id"]);
  return ids;
}

}  // namespace stereomap::testing
