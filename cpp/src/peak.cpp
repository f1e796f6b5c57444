#include "envi/peak.hpp"

#include <Eigen/Core>
#include <algorithm>
#include <chrono>
#include <thread>
#include <vector>

namespace envi {
namespace {

using Packet = Eigen::internal::packet_traits<float>::type;
constexpr int kLanes = Eigen::internal::packet_traits<float>::size;
#ifdef EIGEN_VECTORIZE_AVX512
constexpr int kChains = 24;  // independent accumulators: enough to hide the latency, within 32 registers
#else
constexpr int kChains = 12;
#endif

// `rounds` x 100 multiply-adds on each chain; the sum is returned so none of it is optimised away.
float chains(long rounds) {
  namespace ei = Eigen::internal;
  Packet acc[kChains];
  const Packet m = ei::pset1<Packet>(0.999999f), a = ei::pset1<Packet>(1e-7f);
  for (int c = 0; c < kChains; ++c) acc[c] = ei::pset1<Packet>(float(c));
  for (long r = 0; r < rounds; ++r)
    for (int i = 0; i < 100; ++i)
#pragma GCC unroll 32
      for (int c = 0; c < kChains; ++c) acc[c] = ei::pmadd(acc[c], m, a);
  float s = 0;
  for (int c = 0; c < kChains; ++c) s += ei::predux(acc[c]);
  return s;
}

}  // namespace

double peak_flops(int threads, double seconds) {
  using clock = std::chrono::steady_clock;
  if (threads <= 0) threads = int(std::max(1u, std::thread::hardware_concurrency()));
  long rounds = 1000;  // grown until one pass takes a tenth of the budget
  for (;;) {
    auto t0 = clock::now();
    volatile float sink = chains(rounds);
    (void)sink;
    if (std::chrono::duration<double>(clock::now() - t0).count() > seconds / 10 || rounds > (1L << 40)) break;
    rounds *= 2;
  }
  const long per_thread = rounds * 10;  // about `seconds` on every thread at once
  std::vector<float> sums(static_cast<size_t>(threads));
  auto t0 = clock::now();
  std::vector<std::thread> pool;
  for (int i = 0; i < threads; ++i) pool.emplace_back([&sums, i, per_thread] { sums[size_t(i)] = chains(per_thread); });
  for (auto& t : pool) t.join();
  const double sec = std::chrono::duration<double>(clock::now() - t0).count();
  return double(per_thread) * 100.0 * kChains * kLanes * 2.0 * threads / sec;
}

}  // namespace envi
