// A dense layer packed for the engine's own GEMM microkernel: y = act(W x + b) over a block of
// columns. The accumulators start at the bias and the activation runs on them in registers before
// the one store, where a library GEMM followed by an activation pass reads and writes every output
// twice more. Written with Eigen's packet primitives, so one source serves SSE, AVX2 and AVX-512.
#pragma once
#include <Eigen/Core>
#include <vector>

#include "envi/model.hpp"

namespace envi {

class PackedDense {
 public:
  using Packet = Eigen::internal::packet_traits<float>::type;
  static constexpr int kLanes = Eigen::internal::packet_traits<float>::size;
  static constexpr int kRows = 2 * kLanes;  // output rows per tile: two registers
#ifdef EIGEN_VECTORIZE_AVX512
  static constexpr int kCols = 12;  // 24 accumulators of 32 registers
#else
  static constexpr int kCols = 6;   // 12 accumulators of 16 registers
#endif

  // Worth it only when a tile of output rows is mostly real rows; narrower layers (a model's
  // one-row output) stay with Eigen, which takes its matrix-vector path for them.
  static bool suits(const Dense& d) { return d.W.size() > 0 && d.W.rows() >= kRows; }

  explicit PackedDense(const Dense& d);

  // Floats of scratch `apply` needs: one panel of the input, transposed.
  long scratch_size() const { return in_ * kCols; }

  // x: in x count, column j at x + j * stride; y: out x count, contiguous columns. Allocates nothing.
  void apply(const float* x, long stride, long count, float* y, float* scratch) const;

 private:
  long out_, in_, panels_;
  Act act_;
  float lo_, hi_;
  // Panel p holds rows [p kRows, (p+1) kRows) of W, k-major: kRows floats per input k, zero-padded.
  std::vector<float, Eigen::aligned_allocator<float>> w_, b_;
};

}  // namespace envi
