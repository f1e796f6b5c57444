// Which member of a seed ensemble simulates each run. envi_py.simulate.members_of_runs is the
// Python twin (tests/test_ensemble.py checks the two agree): an equal share per member, to within
// one run, in a seeded random order, so a Python and an envi_sim simulation of one ensemble give
// each run to the same member.
#pragma once
#include <cstdint>
#include <utility>
#include <vector>

namespace envi {

// SplitMix64 (Steele, Lea and Flood 2014): a tiny generator both languages compute bit for bit.
inline uint64_t splitmix64(uint64_t& state) {
  uint64_t z = (state += 0x9E3779B97F4A7C15ULL);
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
  return z ^ (z >> 31);
}

// Member of each of `batch` runs: run g starts as member g mod `members`, then a Fisher-Yates
// shuffle driven by SplitMix64 seeded with `seed` (its modulo bias, below 2^-40 for any batch a
// machine holds, is immaterial).
inline std::vector<int> members_of_runs(int members, long batch, uint64_t seed) {
  std::vector<int> pick(size_t(batch > 0 ? batch : 0));
  for (long g = 0; g < batch; ++g) pick[size_t(g)] = int(g % members);
  uint64_t state = seed;
  for (long i = batch - 1; i > 0; --i) {
    const long j = long(splitmix64(state) % uint64_t(i + 1));
    std::swap(pick[size_t(i)], pick[size_t(j)]);
  }
  return pick;
}

}  // namespace envi
