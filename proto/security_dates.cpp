// The dates a security folder's holder must act on (proto/dds.hpp, securityDatesDue).
#include <openssl/pem.h>
#include <openssl/x509.h>

#include <cstdio>
#include <filesystem>
#include <memory>
#include <optional>

#include "proto/dds.hpp"

namespace stereomap::proto {

namespace {

struct FileCloser {
  void operator()(FILE* f) const { std::fclose(f); }
};

// Days (and seconds) from now to `when`; nullopt when OpenSSL cannot tell.
std::optional<double> daysUntil(const ASN1_TIME* when) {
  int days = 0, seconds = 0;
  if (when == nullptr || ASN1_TIME_diff(&days, &seconds, nullptr, when) != 1) return std::nullopt;
  return days + seconds / 86400.0;
}

std::string say(const std::string& what, double days, const std::string& then) {
  char text[64];
  if (days < 0) {
    std::snprintf(text, sizeof text, "%.1f days ago", -days);
    return what + " ran out " + text + ": " + then;
  }
  std::snprintf(text, sizeof text, "%.1f days", days);
  return what + " runs out in " + text + ": " + then;
}

}  // namespace

std::vector<std::string> securityDatesDue(const std::string& dir, std::chrono::hours ahead) {
  std::vector<std::string> due;
  const double horizon = static_cast<double>(ahead.count()) / 24.0;
  const auto path = std::filesystem::path(dir);
  if (std::unique_ptr<FILE, FileCloser> in{std::fopen((path / "identity.pem").c_str(), "r")}) {
    std::unique_ptr<X509, decltype(&X509_free)> cert(
        PEM_read_X509(in.get(), nullptr, nullptr, nullptr), X509_free);
    if (cert) {
      if (auto days = daysUntil(X509_get0_notAfter(cert.get())); days && *days < horizon) {
        due.push_back(
            say("this participant's certificate (" + (path / "identity.pem").string() + ")", *days,
                "issue a new one with stereomap-certs"));
      }
    }
  }
  if (std::unique_ptr<FILE, FileCloser> in{std::fopen((path / "crl.pem").c_str(), "r")}) {
    std::unique_ptr<X509_CRL, decltype(&X509_CRL_free)> crl(
        PEM_read_X509_CRL(in.get(), nullptr, nullptr, nullptr), X509_CRL_free);
    if (crl) {
      if (auto days = daysUntil(X509_CRL_get0_nextUpdate(crl.get())); days && *days < horizon) {
        due.push_back(say("the revocation list (" + (path / "crl.pem").string() + ")", *days,
                          "past it every handshake fails; renew it (stereomap-certs crl) and "
                          "restart"));
      }
    }
  }
  return due;
}

}  // namespace stereomap::proto
