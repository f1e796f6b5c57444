// The packed microkernel against a plain double-precision loop: layer shapes that fill whole tiles
// and ones that do not (rows not a multiple of a tile, columns not a multiple of a panel, inputs
// read with a stride), every activation it fuses, and a check that it stores nothing outside y.
#include <cmath>
#include <random>
#include <vector>

#include "check.hpp"
#include "envi/dense.hpp"

using namespace envi;

static double reference(const Dense& d, const float* x, int r) {
  double s = d.b(r);
  for (long k = 0; k < d.W.cols(); ++k) s += double(d.W(r, k)) * double(x[k]);
  switch (d.act) {
    case Act::Tanh: return std::tanh(s);
    case Act::Relu: return s > 0 ? s : 0;
    case Act::Sigmoid: return 1 / (1 + std::exp(-s));
    case Act::Clip: return std::fmin(std::fmax(s, d.clip_lo), d.clip_hi);
    default: return s;
  }
}

int main() {
  std::mt19937 gen(7);
  std::normal_distribution<float> normal(0.f, 1.f);
  const int R = PackedDense::kRows, C = PackedDense::kCols;
  struct Shape { long out, in, stride, count; };
  const Shape shapes[] = {{256, 256, 256, 256}, {256, 20, 40, 100}, {R + 3, 17, 17, C + 1}, {R, 1, 5, C},
                          {3 * R - 1, 64, 70, 5 * C - 2}};
  for (const Shape& s : shapes)
    for (Act act : {Act::None, Act::Tanh, Act::Relu, Act::Sigmoid, Act::Clip}) {
      Dense d;
      d.W.resize(s.out, s.in);
      d.b.resize(s.out);
      const float scale = 1.f / std::sqrt(float(s.in));  // pre-activations of order one
      for (long i = 0; i < d.W.size(); ++i) d.W.data()[i] = normal(gen) * scale;
      for (long i = 0; i < s.out; ++i) d.b(i) = normal(gen);
      d.act = act;
      d.clip_lo = -0.5f, d.clip_hi = 0.7f;
      CHECK(PackedDense::suits(d));
      PackedDense p(d);
      std::vector<float> x(size_t(s.stride * s.count));
      for (auto& v : x) v = 3 * normal(gen);
      const float sentinel = 1234.5f;
      std::vector<float> y(size_t(s.out * s.count + 16), sentinel), scratch(size_t(p.scratch_size()));
      p.apply(x.data(), s.stride, s.count, y.data(), scratch.data());
      double worst = 0;
      for (long j = 0; j < s.count; ++j)
        for (int r = 0; r < s.out; ++r)
          worst = std::fmax(worst, std::fabs(y[size_t(j * s.out + r)] - reference(d, x.data() + j * s.stride, r)));
      CHECK(worst <= 2e-5);
      if (worst > 2e-5) std::fprintf(stderr, "out %ld in %ld count %ld act %d: max error %g\n", s.out, s.in, s.count, int(act), worst);
      for (size_t i = size_t(s.out * s.count); i < y.size(); ++i) CHECK(y[i] == sentinel);
    }
  Dense narrow;  // a one-row output layer is left to Eigen
  narrow.W.resize(1, 256);
  narrow.b.resize(1);
  CHECK(!PackedDense::suits(narrow));
  return failures();
}
