// Counter-based random numbers (Philox4x32-10, Salmon et al., SC'11): the draw for (seed, run,
// step, channel) is a pure function of those four numbers, so a stochastic simulation gives the
// same result whatever the thread count, batch size or order in which runs are computed.
#pragma once
#include <cmath>
#include <cstdint>

namespace envi {

inline void philox4x32(uint32_t ctr[4], uint32_t k0, uint32_t k1) {
  constexpr uint32_t M0 = 0xD2511F53u, M1 = 0xCD9E8D57u, W0 = 0x9E3779B9u, W1 = 0xBB67AE85u;
  for (int r = 0; r < 10; ++r) {
    uint64_t p0 = uint64_t(M0) * ctr[0], p1 = uint64_t(M1) * ctr[2];
    uint32_t c0 = uint32_t(p1 >> 32) ^ ctr[1] ^ k0, c2 = uint32_t(p0 >> 32) ^ ctr[3] ^ k1;
    ctr[0] = c0; ctr[1] = uint32_t(p1); ctr[2] = c2; ctr[3] = uint32_t(p0);
    k0 += W0; k1 += W1;
  }
}

// A standard normal draw keyed by (seed, run, step, channel), by Box-Muller on 2 x 53-bit uniforms.
inline double normal(uint64_t seed, uint64_t run, uint32_t step, uint32_t channel) {
  uint32_t c[4] = {uint32_t(run), uint32_t(run >> 32), step, channel};
  philox4x32(c, uint32_t(seed), uint32_t(seed >> 32));
  uint64_t a = (uint64_t(c[0]) << 21) ^ c[1], b = (uint64_t(c[2]) << 21) ^ c[3];
  double u1 = (double(a & ((uint64_t(1) << 53) - 1)) + 1.0) * 0x1p-53;  // (0, 1]: log is finite
  double u2 = double(b & ((uint64_t(1) << 53) - 1)) * 0x1p-53;
  return std::sqrt(-2.0 * std::log(u1)) * std::cos(6.283185307179586 * u2);
}

// A uniform draw in [0, 1) keyed by (seed, run, step, stream), a stream apart from the normals':
// the limit events of a model use channel numbers from 0x80000000 up.
inline double uniform(uint64_t seed, uint64_t run, uint32_t step, uint32_t stream) {
  uint32_t c[4] = {uint32_t(run), uint32_t(run >> 32), step, stream | 0x80000000u};
  philox4x32(c, uint32_t(seed), uint32_t(seed >> 32));
  uint64_t a = (uint64_t(c[0]) << 21) ^ c[1];
  return double(a & ((uint64_t(1) << 53) - 1)) * 0x1p-53;
}

}  // namespace envi
