// 256-bit binary descriptors (ORB) and their Hamming distance by 64-bit popcount.
// Concurrency: plain values and pure functions.
#pragma once

#include <array>
#include <bit>
#include <cstdint>

namespace flatslam {

using Descriptor = std::array<uint64_t, 4>;

[[nodiscard]] inline int DescriptorDistance(const Descriptor& a, const Descriptor& b) {
  return std::popcount(a[0] ^ b[0]) + std::popcount(a[1] ^ b[1]) + std::popcount(a[2] ^ b[2]) +
         std::popcount(a[3] ^ b[3]);
}

}  // namespace flatslam
