// Four floats (or ints) in one register, with GCC's vector extensions (which Clang has too):
// SSE on x86-64, NEON on ARM, without either's intrinsics. For the renderer's first pass, which
// shades four neighbouring pixels of a row at once.
#pragma once

#include <cmath>
#include <cstdint>
#if defined(__SSE__)
#include <xmmintrin.h>
#endif

// On x86-64 a function marked so is also compiled for SSE4.1 (one instruction for a lane
// multiply, four without) and picked at run time; the same results either way.
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define STEREOMAP_LANES_CLONES __attribute__((target_clones("sse4.1", "default")))
#else
#define STEREOMAP_LANES_CLONES
#endif

namespace stereomap::sim::detail {

using F4 = float __attribute__((vector_size(16)));
using I4 = int32_t __attribute__((vector_size(16)));
using U4 = uint32_t __attribute__((vector_size(16)));

// Lane-wise `mask ? a : b` (a mask lane is all ones or all zeros, as comparisons give).
inline F4 select(I4 mask, F4 a, F4 b) { return mask ? a : b; }
inline I4 select(I4 mask, I4 a, I4 b) { return mask ? a : b; }
// As std::min and std::max lane by lane (minps and maxps on SSE).
inline F4 min(F4 a, F4 b) { return b < a ? b : a; }
inline F4 max(F4 a, F4 b) { return a < b ? b : a; }
inline bool any(I4 mask) { return (mask[0] | mask[1] | mask[2] | mask[3]) != 0; }
inline bool all(I4 mask) { return (mask[0] & mask[1] & mask[2] & mask[3]) != 0; }
inline F4 splat(float v) { return F4{v, v, v, v}; }
inline I4 splat(int32_t v) { return I4{v, v, v, v}; }
// Rounded towards minus infinity, as integers (in range).
inline I4 floorInt(F4 v) {
  const I4 i = __builtin_convertvector(v, I4);
  return i + (__builtin_convertvector(i, F4) > v);  // a true lane is -1
}
inline F4 toFloat(I4 v) { return __builtin_convertvector(v, F4); }
inline F4 sqrt(F4 v) {
#if defined(__SSE__)
  return _mm_sqrt_ps(v);
#else
  return F4{std::sqrt(v[0]), std::sqrt(v[1]), std::sqrt(v[2]), std::sqrt(v[3])};
#endif
}

}  // namespace stereomap::sim::detail
