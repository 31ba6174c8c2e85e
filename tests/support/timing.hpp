// Timing for the benchmark binaries: the median wall time of repeated runs.
#pragma once

#include <chrono>
#include <functional>
#include <vector>

#include "common/statistics.hpp"

namespace stereomap::testing {

inline double medianMs(int runs, const std::function<void()>& work) {
  std::vector<double> ms;
  for (int i = 0; i < runs; ++i) {
    const auto start = std::chrono::steady_clock::now();
    work();
    ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
                     .count());
  }
  return common::median(std::move(ms)).value_or(0.0);
}

}  // namespace stereomap::testing
