// Process metrics in Prometheus' text format: counters and gauges with labels, safe to bump
// from any thread. Rendered by GET /metrics.
#pragma once

#include <map>
#include <mutex>
#include <string>
#include <utility>
#include <vector>

namespace stereomap::core {

using Labels = std::vector<std::pair<std::string, std::string>>;

class Metrics {
 public:
  // Declares a metric family once (name, type "counter" or "gauge", help text).
  void describe(const std::string& name, const std::string& type, const std::string& help);
  void add(const std::string& name, const Labels& labels, double value = 1.0);
  void set(const std::string& name, const Labels& labels, double value);
  double get(const std::string& name, const Labels& labels) const;
  // Drops every series of every family that has label `label` with value `value`.
  void removeSeries(const std::string& label, const std::string& value);
  std::string render() const;

 private:
  struct Family {
    std::string type, help;
    std::map<std::string, double> series;  // rendered label set → value
  };
  static std::string labelText(const Labels& labels);
  mutable std::mutex mutex_;
  std::map<std::string, Family> families_;
};

}  // namespace stereomap::core
