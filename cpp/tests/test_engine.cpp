// The engine against a naive reference loop (copies, no batching) for both controllers; Gaussian
// draws independent of threads; controllers and metrics on hand-computed cases.
#include <cmath>
#include <vector>

#include "check.hpp"
#include "envi/controller.hpp"
#include "envi/engine.hpp"
#include "envi/metrics.hpp"
#include "envi/rng.hpp"
#include "onnx_builder.hpp"

using namespace envi;

struct Collect : Sink {
  std::vector<double> out;  // runs x length x channels
  long length;
  int channels;
  std::vector<std::pair<long, int>> blk;
  Collect(long runs, long len, int c, int threads) : out(size_t(runs * len * c)), length(len), channels(c), blk(size_t(threads)) {}
  void begin(int th, long first, int count) override { blk[size_t(th)] = {first, count}; }
  void rows(int th, long t, const double* v) override {
    for (int b = 0; b < blk[size_t(th)].second; ++b)
      for (int k = 0; k < channels; ++k) out[size_t(((blk[size_t(th)].first + b) * length + t) * channels + k)] = v[b * channels + k];
  }
  void end(int) override {}
};

static Model load(const pb::Bytes& b) { return load_model(reinterpret_cast<const uint8_t*>(b.data()), b.size()); }

static std::vector<double> run(const Model& m, const Controller& c, const std::vector<double>& init, long K, long runs,
                               long steps, int threads, int block, uint64_t seed = 0) {
  Job job;
  job.init = init.data();
  job.windows = K;
  job.runs = runs;
  job.steps = steps;
  job.threads = threads;
  job.block = block;
  job.seed = seed;
  Collect sink(K * runs, m.history + steps, m.channels(), plan(job).threads);
  simulate(m, c, job, sink);
  return sink.out;
}

// One run the slow, obvious way: window as a vector, shifted by copying; double-precision layers.
static std::vector<double> reference(const Model& m, const Controller& c, const double* init, long steps) {
  const int C = m.channels(), l = m.history;
  std::vector<double> rows(init, init + l * C), memory(size_t(c.memory_per_run()), 0.0), a(size_t(m.n_action()));
  for (int r = 0; r < l; ++r) c.act(init + r * C, C, a.data(), 1, memory.data());  // warm-up on sigma_0
  for (long t = 0; t < steps; ++t) {
    std::vector<double> x;
    for (int r = 0; r < l; ++r)
      for (int k = 0; k < C; ++k) {
        double v = rows[size_t((rows.size() / C - l + r) * C + k)];
        x.push_back(double(float((v - (m.norm_high[k] + m.norm_low[k]) / 2) / ((m.norm_high[k] - m.norm_low[k]) / 2))));
      }
    for (const auto* part : {&m.trunk, &m.mean})
      for (const Dense& d : *part) {
        std::vector<double> y(size_t(d.W.rows()));
        for (long i = 0; i < d.W.rows(); ++i) {
          double s = d.b[i];
          for (long j = 0; j < d.W.cols(); ++j) s += double(d.W(i, j)) * x[size_t(j)];
          y[size_t(i)] = d.act == Act::Tanh ? std::tanh(s) : s;
        }
        x = y;
      }
    std::vector<double> v(size_t(m.n_state()));
    for (int i = 0; i < m.n_state(); ++i) {
      v[size_t(i)] = double(float(x[size_t(i)])) * (m.norm_high[i] - m.norm_low[i]) / 2 + (m.norm_high[i] + m.norm_low[i]) / 2;
      v[size_t(i)] = std::min(std::max(v[size_t(i)], m.limit_low[i]), m.limit_high[i]);
    }
    c.act(v.data(), m.n_state(), a.data(), 1, memory.data());
    rows.insert(rows.end(), v.begin(), v.end());
    rows.insert(rows.end(), a.begin(), a.end());
  }
  return rows;
}

int main() {
  pb::Spec spec;
  spec.history = 4;
  const long K = 3, runs = 5, steps = 60;  // 15 runs: more than a microkernel panel of columns
  std::vector<double> init;
  for (long k = 0; k < K; ++k)
    for (int r = 0; r < 4; ++r) { init.push_back(20.0 + 15 * k + 5 * r); init.push_back(r % 2 ? 30 : -30); }
  // Widths below and above a microkernel tile of rows on every instruction set (Eigen or packed).
  for (int hidden : {6, 40}) {
    spec.hidden = hidden;
    Model m = load(pb::model(spec));
    for (const char* js : {R"({"name": "lane-keeping", "params": {"x": 30}})",
                           R"({"name": "pid", "params": {"kp": 2, "ki": 8, "kd": 0.1, "out_min": -30, "out_max": 30}})"}) {
      Controller c = Controller::parse(js);
      std::vector<double> got = run(m, c, init, K, runs, steps, 2, 256);
      double worst = 0;
      for (long g = 0; g < K * runs; ++g) {
        std::vector<double> want = reference(m, c, init.data() + (g / runs) * 8, steps);
        for (size_t i = 0; i < want.size(); ++i) worst = std::max(worst, std::fabs(want[i] - got[size_t(g) * want.size() + i]));
      }
      CHECK(worst < 1e-2);  // float32 engine vs double reference; a logic error would be O(1)
      std::printf("hidden %d, %s: max |engine - reference| = %.2e\n", hidden, c.name().c_str(), worst);
    }
  }

  // Two states and two actions with a combine: each action its own loop, warm-up included.
  spec.hidden = 40;
  spec.n_state = spec.n_action = 2;
  {
    Model m2 = load(pb::model(spec));
    std::vector<double> init2;
    for (long k = 0; k < K; ++k)
      for (int r = 0; r < 4; ++r) {
        init2.insert(init2.end(), {20.0 + 15 * k + 5 * r, 70.0 - 10 * r});
        init2.insert(init2.end(), {r % 2 ? 30.0 : -30.0, double(r)});
      }
    Controller c = Controller::parse(R"({"name": "combine", "params": {"loops": [)"
                                     R"({"name": "pid", "params": {"kp": 2, "ki": 8, "kd": 0.1, "input": 1, "out_min": -30, "out_max": 30}}, )"
                                     R"({"name": "bang-bang", "params": {"x": 12}}]}})");
    std::vector<double> got = run(m2, c, init2, K, runs, steps, 2, 256);
    double worst = 0, spread = 0;
    for (long g = 0; g < K * runs; ++g) {
      std::vector<double> want = reference(m2, c, init2.data() + (g / runs) * 16, steps);
      for (size_t i = 0; i < want.size(); ++i) worst = std::max(worst, std::fabs(want[i] - got[size_t(g) * want.size() + i]));
      for (size_t i = 16; i < want.size(); i += 4) spread = std::max(spread, std::fabs(want[i + 2] - want[i + 3]));
    }
    CHECK(worst < 1e-2);
    CHECK(spread > 1);  // the two actions differ: nothing is broadcast
    std::printf("2 states/2 actions, combine: max |engine - reference| = %.2e\n", worst);
    CHECK_THROWS(WidthError, run(m2, Controller::parse(R"({"name": "pid"})"), init2, K, 1, 3, 1, 8), "drives 1 action channel(s), the model has 2");
  }
  spec.n_state = spec.n_action = 1;
  spec.hidden = 16;

  // Gaussian: the same draws whatever the thread count; different seeds differ.
  spec.gaussian = true;
  Model g = load(pb::model(spec));
  Controller lk = Controller::parse(R"({"name": "lane-keeping"})");
  auto a = run(g, lk, init, K, 5, 30, 1, 4, 7), b = run(g, lk, init, K, 5, 30, 3, 4, 7), c = run(g, lk, init, K, 5, 30, 1, 4, 8);
  CHECK(a == b);
  CHECK(a != c);

  // Philox: a known-answer vector from the Random123 distribution (philox4x32-10, zero key and counter).
  uint32_t ctr[4] = {0, 0, 0, 0};
  philox4x32(ctr, 0, 0);
  CHECK(ctr[0] == 0x6627e8d5u && ctr[1] == 0xe169c58du && ctr[2] == 0xbc57ac4cu && ctr[3] == 0x9b00dbd8u);
  double s1 = 0, s2 = 0;
  for (uint32_t i = 0; i < 200000; ++i) { double z = normal(1, i, 0, 0); s1 += z; s2 += z * z; }
  CHECK(std::fabs(s1 / 200000) < 0.01 && std::fabs(s2 / 200000 - 1) < 0.02);

  // Controllers: lane-keeping sign; PID anti-windup freezes the integral while saturated.
  double st[3] = {50, 40, 10}, act[3];
  lk.act(st, 1, act, 3, nullptr);
  CHECK(act[0] == 30 && act[1] == 0 && act[2] == -30);
  Controller pid = Controller::parse(R"({"name": "pid", "params": {"kp": 1, "ki": 10, "dt": 0.5, "setpoint": 0, "out_max": 4}})");
  double s = 2, u, pm[3] = {7, 7, 7};
  pid.reset(pm, 1);
  pid.act(&s, 1, &u, 1, pm);  // raw = 2 + 10 * 1 = 12 -> 4, integral stays 0
  CHECK(u == 4 && pm[0] == 0);
  s = -1;
  pid.act(&s, 1, &u, 1, pm);  // raw = -1 + 10 * (0 - 0.5) = -6 (in range) -> integral -0.5
  CHECK(u == -6 && pm[0] == -0.5);

  // Metrics: skip 2, band 30..50: samples 45 60 70 45 20 20 45 -> steady 3 episodes/3 samples,
  // over 1 episode (amplitude 20, 2 samples), under 1 episode (amplitude 10, 2 samples).
  const double tr[9] = {99, 99, 45, 60, 70, 45, 20, 20, 45};
  double out[8];
  driving_metrics(tr, 1, 9, MetricConfig{40, 10, 2, 0}, out);
  const double want[8] = {3, 3, 1, 20, 2, 1, 10, 2};
  for (int i = 0; i < 8; ++i) CHECK(out[i] == want[i]);
  CHECK_THROWS(std::invalid_argument, driving_metrics(tr, 1, 9, MetricConfig{40, 10, 9, 0}, out), "nothing to score");
  std::printf("test_engine: %d failure(s)\n", failures());
  return failures() ? 1 : 0;
}
