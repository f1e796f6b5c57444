#include "envi/dense.hpp"

#include <algorithm>

namespace envi {
namespace {

using Packet = PackedDense::Packet;
constexpr int L = PackedDense::kLanes;
constexpr int R = PackedDense::kRows;
constexpr int C = PackedDense::kCols;
namespace ei = Eigen::internal;

inline Packet activate(Packet v, Act act, float lo, float hi) {
  switch (act) {
    case Act::Tanh: return ei::ptanh(v);  // Eigen's own, as its .tanh() on arrays
    case Act::Relu: return ei::pmax(v, ei::pzero(v));
    case Act::Clip: return ei::pmin(ei::pmax(v, ei::pset1<Packet>(lo)), ei::pset1<Packet>(hi));
    default: return v;  // None; Sigmoid is applied after the store (see apply)
  }
}

// One tile: kRows output rows x kCols columns, the whole reduction over k in registers.
inline void tile(const float* w, const float* xp, long k_len, const float* bias, Act act, float lo, float hi,
                 float* y, long ldy, long rows, long cols) {
  Packet a0[C], a1[C];
  const Packet b0 = ei::pload<Packet>(bias), b1 = ei::pload<Packet>(bias + L);
#pragma GCC unroll 16
  for (int c = 0; c < C; ++c) a0[c] = b0, a1[c] = b1;
  for (long k = 0; k < k_len; ++k, w += R, xp += C) {
    const Packet w0 = ei::pload<Packet>(w), w1 = ei::pload<Packet>(w + L);
#pragma GCC unroll 16
    for (int c = 0; c < C; ++c) {
      const Packet x = ei::pset1<Packet>(xp[c]);
      a0[c] = ei::pmadd(w0, x, a0[c]);
      a1[c] = ei::pmadd(w1, x, a1[c]);
    }
  }
  for (int c = 0; c < C && c < cols; ++c) {
    const Packet v0 = activate(a0[c], act, lo, hi), v1 = activate(a1[c], act, lo, hi);
    float* col = y + c * ldy;
    if (rows == R) {
      ei::pstoreu(col, v0);
      ei::pstoreu(col + L, v1);
    } else {  // the last panel of a layer whose width is not a multiple of kRows
      alignas(64) float tmp[R];
      ei::pstore(tmp, v0);
      ei::pstore(tmp + L, v1);
      std::copy_n(tmp, rows, col);
    }
  }
}

}  // namespace

PackedDense::PackedDense(const Dense& d)
    : out_(d.W.rows()), in_(d.W.cols()), panels_((d.W.rows() + R - 1) / R), act_(d.act),
      lo_(d.clip_lo), hi_(d.clip_hi) {
  w_.assign(size_t(panels_ * R * in_), 0.f);
  b_.assign(size_t(panels_ * R), 0.f);
  for (long p = 0; p < panels_; ++p)
    for (long k = 0; k < in_; ++k)
      for (long r = 0; r < R && p * R + r < out_; ++r) w_[size_t((p * in_ + k) * R + r)] = d.W(p * R + r, k);
  for (long r = 0; r < out_; ++r) b_[size_t(r)] = d.b(r);
}

void PackedDense::apply(const float* x, long stride, long count, float* y, float* scratch) const {
  for (long j = 0; j < count; j += C) {
    const long cols = std::min<long>(C, count - j);
    // The panel's inputs, k-major so a tile broadcasts them from one running pointer; missing
    // columns of the last panel are zeros whose results are never stored.
    for (long k = 0; k < in_; ++k)
      for (long c = 0; c < C; ++c) scratch[k * C + c] = c < cols ? x[(j + c) * stride + k] : 0.f;
    for (long p = 0; p < panels_; ++p)
      tile(w_.data() + p * in_ * R, scratch, in_, b_.data() + p * R, act_, lo_, hi_, y + j * out_ + p * R, out_,
           std::min<long>(R, out_ - p * R), cols);
  }
  if (act_ == Act::Sigmoid) {  // rare in these models: Eigen's logistic, as the unpacked path
    Eigen::Map<Eigen::ArrayXf> v(y, out_ * count);
    v = v.logistic();
  }
}

}  // namespace envi
