#include "tests/support/udp_delay_relay.hpp"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <poll.h>
#include <sched.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <deque>
#include <stdexcept>

namespace stereomap::testing {

namespace {

using Clock = std::chrono::steady_clock;

sockaddr_in addressOf(const std::string& ip, int port) {
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(static_cast<uint16_t>(port));
  ::inet_pton(AF_INET, ip.c_str(), &address.sin_addr);
  return address;
}

struct Datagram {
  Clock::time_point due;
  size_t socket;
  std::vector<uint8_t> bytes;
};

}  // namespace

UdpDelayRelay::UdpDelayRelay(const std::string& netns, const std::string& listen_address,
                             const std::string& target_address, const std::vector<int>& ports,
                             std::chrono::milliseconds delay) {
  thread_ = std::thread([=, this] { run(netns, listen_address, target_address, ports, delay); });
  while (!ready_) std::this_thread::sleep_for(std::chrono::milliseconds(5));
  if (!error_.empty()) {
    thread_.join();
    throw std::runtime_error("UDP delay relay: " + error_);
  }
}

UdpDelayRelay::~UdpDelayRelay() {
  stop_ = true;
  if (thread_.joinable()) thread_.join();
}

void UdpDelayRelay::run(const std::string& netns, const std::string& listen_address,
                        const std::string& target_address, const std::vector<int>& ports,
                        std::chrono::milliseconds delay) {
  std::vector<pollfd> sockets;
  auto fail = [&](const std::string& what) {
    error_ = what;
    for (const auto& s : sockets) ::close(s.fd);
    ready_ = true;
  };
  // This thread only: setns moves the calling thread.
  const int ns = ::open(("/run/netns/" + netns).c_str(), O_RDONLY | O_CLOEXEC);
  if (ns < 0 || ::setns(ns, CLONE_NEWNET) != 0) {
    if (ns >= 0) ::close(ns);
    return fail("cannot enter " + netns);
  }
  ::close(ns);
  for (const int port : ports) {
    const int fd = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
    const sockaddr_in address = addressOf(listen_address, port);
    if (fd < 0 || ::bind(fd, reinterpret_cast<const sockaddr*>(&address), sizeof address) != 0) {
      if (fd >= 0) ::close(fd);
      return fail("cannot bind " + listen_address + ":" + std::to_string(port));
    }
    sockets.push_back({fd, POLLIN, 0});
  }
  ready_ = true;

  std::deque<Datagram> queue;  // in arrival order, so in order of due time
  std::vector<uint8_t> buffer(65536);
  while (!stop_) {
    int wait_ms = 50;
    if (!queue.empty()) {
      const auto until =
          std::chrono::duration_cast<std::chrono::milliseconds>(queue.front().due - Clock::now());
      wait_ms = std::clamp<int>(static_cast<int>(until.count()), 0, 50);
    }
    ::poll(sockets.data(), sockets.size(), wait_ms);
    for (size_t i = 0; i < sockets.size(); ++i) {
      if ((sockets[i].revents & POLLIN) == 0) continue;
      ssize_t n;
      while ((n = ::recv(sockets[i].fd, buffer.data(), buffer.size(), 0)) > 0) {
        queue.push_back({Clock::now() + delay, i, {buffer.begin(), buffer.begin() + n}});
      }
    }
    while (!queue.empty() && queue.front().due <= Clock::now()) {
      const Datagram& d = queue.front();
      const sockaddr_in target = addressOf(target_address, ports[d.socket]);
      ::sendto(sockets[d.socket].fd, d.bytes.data(), d.bytes.size(), 0,
               reinterpret_cast<const sockaddr*>(&target), sizeof target);
      ++forwarded_;
      queue.pop_front();
    }
  }
  for (const auto& s : sockets) ::close(s.fd);
}

}  // namespace stereomap::testing
