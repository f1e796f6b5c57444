// A residual mean head: the loader refuses a graph and metadata that disagree, and one step of the
// engine is 2 tanh(head) + base, the base written out here by hand for windows whose saturating
// state is never, partly and entirely at its limit.
#include <cmath>
#include <vector>

#include "check.hpp"
#include "envi/controller.hpp"
#include "envi/engine.hpp"
#include "envi/rng.hpp"
#include "onnx_builder.hpp"

using namespace envi;

static Model load(const pb::Bytes& b) { return load_model(reinterpret_cast<const uint8_t*>(b.data()), b.size()); }

struct FirstStep : Sink {  // each run's first simulated row (one thread)
  std::vector<double> out;
  long row, first = 0;
  int channels, count = 0;
  FirstStep(long runs, long r, int c) : out(size_t(runs * c)), row(r), channels(c) {}
  void begin(int, long f, int n) override { first = f, count = n; }
  void rows(int, long t, const double* v) override {
    if (t == row) std::copy(v, v + long(count) * channels, out.begin() + first * channels);
  }
  void end(int) override {}
};

// Layers in double, as the reference of test_engine.cpp.
static std::vector<double> apply(const std::vector<Dense>& layers, std::vector<double> x) {
  for (const Dense& d : layers) {
    std::vector<double> y(size_t(d.W.rows()));
    for (long i = 0; i < d.W.rows(); ++i) {
      double s = d.b[i];
      for (long j = 0; j < d.W.cols(); ++j) s += double(d.W(i, j)) * x[size_t(j)];
      y[size_t(i)] = d.act == Act::Tanh ? std::tanh(s) : d.act == Act::Clip ? std::min(std::max(s, double(d.clip_lo)), double(d.clip_hi)) : s;
    }
    x = y;
  }
  return x;
}

// The first simulated state of run `run` from `window` (l x C physical), the obvious way: the base
// is each state's last reading, for the limit state (reading 80) its last reading that is not 80
// (unless `limit_base` is false: the wrong base a plain skip connection would take).
static std::vector<double> reference(const Model& m, const std::vector<double>& window, int limit_state, uint64_t seed, long run,
                                     bool limit_base) {
  const int C = m.channels(), l = m.history, ns = m.n_state();
  std::vector<double> x;
  for (int r = 0; r < l; ++r)
    for (int k = 0; k < C; ++k)
      x.push_back(double(float((window[size_t(r * C + k)] - (m.norm_high[k] + m.norm_low[k]) / 2) / ((m.norm_high[k] - m.norm_low[k]) / 2))));
  std::vector<double> h = apply(m.trunk, x), head = apply(m.mean, h);
  std::vector<double> out(static_cast<size_t>(ns));
  for (int i = 0; i < ns; ++i) {
    int from = l - 1;
    if (i == limit_state && limit_base) {
      while (from >= 0 && window[size_t(from * C + i)] == 80.0) --from;
      if (from < 0) from = l - 1;
    }
    double mu = 2 * head[size_t(i)] + x[size_t(from * C + i)];
    if (m.gaussian()) mu += std::exp(apply(m.log_std, h)[size_t(i)]) * normal(seed, uint64_t(run), 0, uint32_t(i));
    double v = mu * (m.norm_high[i] - m.norm_low[i]) / 2 + (m.norm_high[i] + m.norm_low[i]) / 2;
    out[size_t(i)] = m.clamp ? std::min(std::max(v, m.limit_low[i]), m.limit_high[i]) : v;
  }
  if (limit_state >= 0 && uniform(seed, uint64_t(run), 0, 0) < 1 / (1 + std::exp(-apply(m.event, h)[0])))
    out[size_t(limit_state)] = 80.0;
  return out;
}

// One step of the engine from each window; the worst difference from the reference over the states
// (and how many steps put the limit state at its limit reading, 80).
static double worst_step(const Model& m, const std::vector<std::vector<double>>& windows, int limit_state, bool limit_base = true,
                         int* at_limit = nullptr) {
  std::vector<double> init;
  for (const auto& w : windows) init.insert(init.end(), w.begin(), w.end());
  Job job;
  job.init = init.data();
  job.windows = long(windows.size());
  job.steps = 1;
  job.seed = 11;
  job.threads = 1;
  FirstStep sink(job.windows, m.history, m.channels());
  simulate(m, Controller::parse(R"({"name": "pid", "params": {"ki": 1}})"), job, sink);
  double worst = 0;
  for (size_t k = 0; k < windows.size(); ++k) {
    std::vector<double> want = reference(m, windows[k], limit_state, job.seed, long(k), limit_base);
    for (int i = 0; i < m.n_state(); ++i)
      worst = std::max(worst, std::fabs(want[size_t(i)] - sink.out[k * size_t(m.channels()) + size_t(i)]));
    if (at_limit && limit_state >= 0) *at_limit += sink.out[k * size_t(m.channels()) + size_t(limit_state)] == 80.0;
  }
  return worst;
}

// A window of 4 rows (colour0, colour1, angle) with colour1's readings as given.
static std::vector<double> window(std::vector<double> limit_column, double last_colour0 = 35.0) {
  std::vector<double> w;
  for (int r = 0; r < 4; ++r) w.insert(w.end(), {20.0 + 5 * r, limit_column[size_t(r)], r % 2 ? 10.0 : -10.0});
  w[9] = last_colour0;
  return w;
}

int main() {
  pb::Spec spec;
  spec.history = 4;
  spec.n_state = 2;
  spec.n_action = 1;
  spec.residual = true;
  spec.clamp = false;  // states as the model says them, not pinned to the range's ends

  // The last row's states: a Slice, no limits.
  Model plain = load(pb::model(spec));
  CHECK(plain.residual.on && plain.residual.scale == 2.f && plain.residual.limits.empty());
  double worst = worst_step(plain, {window({30, 40, 50, 60}), window({60, 50, 80, 80}, 80)}, -1);
  CHECK(worst < 1e-3);
  std::printf("residual, no limit: max |engine - reference| = %.2e\n", worst);

  // Colour1 saturates at 80: never, entirely, at the end, in gaps and at the start of the window.
  // Colour0 at 80 in the last row has no limit: its base stays 80.
  spec.gaussian = true;
  spec.limit_state = 1;
  Model lim = load(pb::model(spec));
  CHECK(lim.residual.on && lim.residual.limits.size() == 1 && lim.residual.limits[0].state == 1 &&
        lim.residual.limits[0].level == 1.f && lim.residual.tolerance == 1e-5f);
  std::vector<std::vector<double>> windows;
  for (int copy = 0; copy < 8; ++copy)  // each copy is another run: other draws, some of them limit events
    for (const auto& w : {window({30, 40, 50, 60}), window({80, 80, 80, 80}), window({30, 40, 80, 80}),
                          window({80, 40, 80, 60}), window({80, 80, 80, 50}, 80), window({30, 80, 80, 80}, 80)})
      windows.push_back(w);
  int events = 0;
  worst = worst_step(lim, windows, 1, true, &events);
  CHECK(worst < 1e-3);
  CHECK(events > 0 && events < int(windows.size()) / 2);
  std::printf("residual with a limit event: max |engine - reference| = %.2e\n", worst);
  // the base matters: a reference taking colour1's last reading whatever it is lies far off
  CHECK(worst_step(lim, windows, 1, false) > 1);

  // Graph and metadata that disagree.
  pb::Spec s = spec;
  s.residual_meta = "null";
  CHECK_THROWS(ModelError, load(pb::model(s)), "belongs to a residual mean head, but metadata 'envi.residual' declares none");
  s = spec;
  s.residual = false;
  s.residual_meta = R"({"scale": 2.0, "tolerance": 1e-05, "limit_levels": [[1, 1.0]]})";
  CHECK_THROWS(ModelError, load(pb::model(s)), "the graph has no node 'residual.rows'");
  s = spec;
  s.residual_meta = R"({"scale": 3.0, "tolerance": 1e-05, "limit_levels": [[1, 1.0]]})";
  CHECK_THROWS(ModelError, load(pb::model(s)), "initializer 'residual.scale' does not hold what metadata 'envi.residual' implies");
  s.residual_meta = R"({"scale": 2.0, "tolerance": 1e-04, "limit_levels": [[1, 1.0]]})";
  CHECK_THROWS(ModelError, load(pb::model(s)), "'residual.tolerance'");
  s.residual_meta = R"({"scale": 2.0, "tolerance": 1e-05, "limit_levels": []})";
  CHECK_THROWS(ModelError, load(pb::model(s)), "limit_levels must name the states of 'envi.limit_events'");
  s.residual_meta = R"({"scale": -2.0, "tolerance": 1e-05, "limit_levels": [[1, 1.0]]})";
  CHECK_THROWS(ModelError, load(pb::model(s)), "positive scale");
  s.residual_meta = R"({"scale": 2.0, "tolerance": 1e-05, "limit_levels": [[5, 1.0]]})";
  CHECK_THROWS(ModelError, load(pb::model(s)), "[state index, normalised level] pairs");
  s.residual_meta = R"({"scale": 2.0})";
  CHECK_THROWS(ModelError, load(pb::model(s)), "envi metadata");
  s = spec;
  s.limit_state = -1;  // a plain Slice graph where the metadata declares a limit: the event head is missing too
  s.residual_meta = R"({"scale": 2.0, "tolerance": 1e-05, "limit_levels": [[1, 1.0]]})";
  CHECK_THROWS(ModelError, load(pb::model(s)), "limit_events");
  // a stray node in the residual group, and one node changed
  CHECK_THROWS(ModelError, load(pb::model(spec, {pb::node("Identity", {"residual.base"}, "copy", {}, "", "residual.copy")})),
               "graph node 'residual.copy' is not part of the residual mean head");
  pb::Bytes g = pb::model(spec);
  const pb::Bytes last = pb::attr_int("select_last_index", 1);
  size_t at = g.find(last);
  CHECK(at != pb::Bytes::npos);
  g.replace(at, last.size(), pb::attr_int("select_last_index", 0));  // the first row in range, not the last
  CHECK_THROWS(ModelError, load(g), "'residual.last_in_range' must be ArgMax(residual.in_range_float, axis=1, select_last_index=1)");
  // an int64 constant where a weight belongs
  CHECK_THROWS(ModelError, load(pb::model(spec, {pb::node("MatMul", {"a0", "residual.axis"}, "z")})), "must be float32");

  std::printf("test_residual: %d failure(s)\n", failures());
  return failures() ? 1 : 0;
}
