// A link's one-way delay where the kernel has no netem: UDP datagrams arriving at
// `listen_address` on each of `ports` are sent on to `target_address`, same port, `delay`
// later, from a thread of its own inside a network namespace. With the server's DDS
// advertising the relay's address (STEREOMAP_DDS_EXTERNAL_ADDRESS) and the vehicle's peer
// set to it, everything the vehicle sends the server takes the relay's way.
#pragma once

#include <atomic>
#include <chrono>
#include <string>
#include <thread>
#include <vector>

namespace stereomap::testing {

class UdpDelayRelay {
 public:
  UdpDelayRelay(const std::string& netns, const std::string& listen_address,
                const std::string& target_address, const std::vector<int>& ports,
                std::chrono::milliseconds delay);
  ~UdpDelayRelay();
  UdpDelayRelay(const UdpDelayRelay&) = delete;
  UdpDelayRelay& operator=(const UdpDelayRelay&) = delete;

  uint64_t forwarded() const { return forwarded_; }

 private:
  void run(const std::string& netns, const std::string& listen_address,
           const std::string& target_address, const std::vector<int>& ports,
           std::chrono::milliseconds delay);

  std::atomic<bool> stop_{false};
  std::atomic<bool> ready_{false};
  std::atomic<uint64_t> forwarded_{0};
  std::string error_;
  std::thread thread_;
};

}  // namespace stereomap::testing
