// Run-time CPU feature checks for the kernels that have a vector path.
// Concurrency: pure function, callable from any thread.
#pragma once

namespace flatslam {

// True when this CPU executes AVX2 instructions.
[[nodiscard]] inline bool HasAvx2() {
#if defined(__x86_64__) || defined(__i386__)
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx2");
#else
  return false;
#endif
}

// True when this CPU executes AVX2 and fused multiply-add instructions.
[[nodiscard]] inline bool HasAvx2Fma() {
#if defined(__x86_64__) || defined(__i386__)
  return HasAvx2() && __builtin_cpu_supports("fma");
#else
  return false;
#endif
}

}  // namespace flatslam
