// The arithmetic peak of this build: fused multiply-adds on the widest vectors it was compiled
// for, all in registers. Benchmarks use it as the hard ceiling next to a library GEMM's rate, which
// can sit well below it when the library does not use the machine's widest vectors.
#pragma once

namespace envi {

// FLOP per second on `threads` threads (0: one per core), measured for about `seconds`.
double peak_flops(int threads, double seconds);

}  // namespace envi
