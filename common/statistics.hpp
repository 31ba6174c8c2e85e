// Small statistics over samples that several modules take (medians of ratios, depths, times).
#pragma once

#include <algorithm>
#include <cstddef>
#include <optional>
#include <vector>

namespace stereomap::common {

// The median of `values` (for an even count, the upper of the two middle values), or
// nullopt when there are none. Takes the vector by value: it is partly reordered.
template <class T>
std::optional<T> median(std::vector<T> values) {
  if (values.empty()) return std::nullopt;
  const auto middle = values.begin() + static_cast<std::ptrdiff_t>(values.size() / 2);
  std::nth_element(values.begin(), middle, values.end());
  return *middle;
}

}  // namespace stereomap::common
