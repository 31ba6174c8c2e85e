// Two network namespaces joined by a veth pair, for tests of a vehicle on a thin radio link:
// the server on one side, the vehicle on the other, each with a DDS configuration of its own
// (its veth as the interface, no multicast, the other end as the peer, datagrams that fit
// the link's MTU). Made with ip(8), shaped with tc's tbf and random loss by nftables, and
// removed again at the end. Needs root.
//
//   LinkedNamespaces link("shaped");
//   link.shape({.rate = "1mbit", .loss_percent = 1});
//   { auto in = link.enter(link.server()); ServerProcess server(...); }  // starts in it
#pragma once

#include <chrono>
#include <memory>
#include <optional>
#include <string>

#include "tests/support/udp_delay_relay.hpp"

namespace stereomap::testing {

struct LinkShape {
  std::string rate;      // tc's notation, "1mbit"; "" leaves the rate alone
  int loss_percent = 0;  // random drops of outgoing packets, each direction
};

class LinkedNamespaces {
 public:
  struct Side {
    std::string ns, dev, address;
    std::string dds_peer;      // where its DDS finds the other side
    std::string dds_external;  // the address its DDS advertises, when not its own ("")
  };

  // Why namespaces cannot be made here (not root, no ip, tc or nft), or nullopt when they can.
  static std::optional<std::string> unavailable();

  // `tag`: a few letters that keep names apart (interface names hold 15 characters).
  // Namespaces that a killed earlier run left behind are removed first.
  explicit LinkedNamespaces(const std::string& tag, int subnet = 0);
  ~LinkedNamespaces();
  LinkedNamespaces(const LinkedNamespaces&) = delete;
  LinkedNamespaces& operator=(const LinkedNamespaces&) = delete;

  const Side& server() const { return server_; }
  const Side& vehicle() const { return vehicle_; }

  // tbf at `rate` (a 400 ms queue) and random loss on both sides' outgoing packets.
  void shape(const LinkShape& shape);

  // Delays what the vehicle sends the server by `delay`: a UdpDelayRelay in the vehicle's
  // namespace, on an address of its own, forwards the server's DDS ports (`dds_domain`,
  // participant indexes 0-3); the server advertises that address, the vehicle peers with it.
  // Before the processes start.
  void delayToServer(std::chrono::milliseconds delay, int dds_domain);

  // While alive, the calling thread is in `side`'s namespace: its sockets, and processes it
  // starts, are there; and STEREOMAP_DDS_INTERFACE, _PEER and _EXTERNAL_ADDRESS are set as
  // config/cyclonedds-radio.xml wants them for that side. Back where it was after.
  class Entered {
   public:
    explicit Entered(const Side& side);
    ~Entered();
    Entered(const Entered&) = delete;
    Entered& operator=(const Entered&) = delete;

   private:
    int previous_ = -1;
  };
  Entered enter(const Side& side) const { return Entered(side); }
  uint64_t relayed() const { return relay_ ? relay_->forwarded() : 0; }

  // Bytes waiting in `side`'s queue and packets it dropped (tc -s qdisc), and packets the
  // random loss dropped (nft's counter).
  struct QueueStats {
    long backlog_bytes = 0;
    long dropped = 0;
    long lost = 0;
  };
  QueueStats queue(const Side& side) const;

 private:
  static void sweepStale();

  Side server_, vehicle_;
  std::unique_ptr<UdpDelayRelay> relay_;
};

}  // namespace stereomap::testing
