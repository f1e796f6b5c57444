#include "envi/engine.hpp"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <exception>
#include <mutex>
#include <stdexcept>
#include <thread>
#include <vector>

#include "envi/dense.hpp"
#include "envi/rng.hpp"

namespace envi {
namespace {

using MatF = Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic>;
using InMap = Eigen::Map<const MatF, 0, Eigen::OuterStride<>>;
using OutMap = Eigen::Map<MatF>;

void activate(OutMap& y, const Dense& d) {
  switch (d.act) {
    case Act::None: break;
    case Act::Tanh: y.array() = y.array().tanh(); break;
    case Act::Relu: y.array() = y.array().max(0.f); break;
    case Act::Sigmoid: y.array() = y.array().logistic(); break;
    case Act::Clip: y.array() = y.array().max(d.clip_lo).min(d.clip_hi); break;
  }
}

// Layers applied to `in` (rows x count, column stride `stride`), ping-ponging between two buffers.
// Packed layers run the engine's microkernel when the block fills at least one tile of columns (a
// single run is a matrix-vector product, Eigen's GEMV does it better); the rest runs Eigen, with
// the bias written first and the product accumulated onto it (one pass fewer than adding it after).
const float* forward(const Dense* first, const Dense* last, const float* in, long rows, long stride, long count,
                     float* a, float* b, float* scratch) {
  for (const Dense* it = first; it != last; ++it) {
    const Dense& d = *it;
    float* outp = (in == a) ? b : a;
    if (d.packed && count >= PackedDense::kCols) {
      d.packed->apply(in, stride, count, outp, scratch);
      rows = d.W.rows();
    } else if (d.W.size() == 0) {  // activation on its own
      OutMap y(outp, rows, count);
      y = InMap(in, rows, count, Eigen::OuterStride<>(stride));
      activate(y, d);
    } else {
      OutMap y(outp, d.W.rows(), count);
      y = d.b.replicate(1, count);
      y.noalias() += d.W * InMap(in, rows, count, Eigen::OuterStride<>(stride));
      activate(y, d);
      rows = d.W.rows();
    }
    in = outp;
    stride = rows;
  }
  return in;
}

const float* forward(const std::vector<Dense>& layers, const float* in, long rows, long stride, long count,
                     float* a, float* b, float* scratch) {
  return forward(layers.data(), layers.data() + layers.size(), in, rows, stride, count, a, b, scratch);
}

struct Workspace {
  MatF ring;                       // (2 l C) x block: each run's window rows, twice (see below)
  std::vector<float> buf[4];       // hidden activations, ping-pong pairs for trunk and heads
  MatF mean;                       // n_state x block
  MatF context_bias;               // first trunk layer's width x block: context_W * each run's context
  std::vector<unsigned char> events;  // limit events x block: which happen this step
  std::vector<float> scratch;      // the packed layers' input panel
  std::vector<double> rows, states, actions, memory;
  std::vector<double> seen, view, layer_memory;  // effect layers: see Runner::layer_states / layer_commands

  Workspace(const Model& m, const Controller& ctrl, int block, long layer_memory_per_run) {
    long c = m.channels();
    long panel = 1;
    for (const auto* layers : {&m.trunk, &m.mean, &m.log_std, &m.event})
      for (const Dense& d : *layers)
        if (d.packed) panel = std::max(panel, d.packed->scratch_size());
    scratch.resize(size_t(panel));
    ring.resize(2 * m.history * c, block);
    for (auto& v : buf) v.resize(size_t(m.max_width()) * size_t(block));
    mean.resize(m.n_state(), block);
    if (m.context) context_bias.resize(m.context_W.rows(), block);
    events.resize(size_t(m.limit_events.size()) * size_t(block));
    rows.resize(size_t(block) * size_t(c));
    states.resize(size_t(block) * size_t(m.n_state()));
    actions.resize(size_t(block) * size_t(m.n_action()));
    memory.resize(size_t(block) * size_t(ctrl.memory_per_run()));
    if (!m.layers.empty()) {
      seen.resize(states.size());
      view.resize(rows.size());
      layer_memory.resize(size_t(block) * size_t(layer_memory_per_run));
    }
  }
};

// Keys of the effect layers' draws, apart from the Gaussian head's (channel < number of states) and
// the limit events' (uniform streams from 0x80000000): layer `k`'s noise on state i at step t uses
// channel kLayerStream | k << 16 | i, its per-run gain step kRunGainStep.
constexpr uint32_t kLayerStream = 0x40000000u;
// A Student-t step noise's chi-square draws: state i's j-th at channel kDofStream | i << 8 | j.
constexpr uint32_t kDofStream = 0x20000000u;
// A two-scale step noise's choice of scale: state i's uniform stream kMixStream | i.
constexpr uint32_t kMixStream = 0x10000000u;
constexpr uint32_t kRunGainStep = 0xFFFFFFFFu;

struct Runner {
  const Model& m;
  const Controller& ctrl;
  const Job& job;
  Sink& sink;
  std::vector<double> centre, half;
  long trunk_out;  // width of the trunk's output (the window itself without a trunk)
  // A residual head's limit level per state; +inf for a state without one, whose every reading is in range.
  std::vector<float> level;
  // Each effect layer's offset in a run's layer memory (a delay's ring of k+1 commands and sigma_0's
  // first command, a lag's or a play's position, a run's gain), and the memory a run needs in all.
  std::vector<long> layer_offset;
  long layer_memory = 0;
  bool have_state_layers = false;  // noise, quantise or saturation: a sensor's reading is then re-made

  Runner(const Model& model, const Controller& c, const Job& j, Sink& s)
      : m(model), ctrl(c), job(j), sink(s) {
    using K = Model::EffectLayer::Kind;
    const long na = m.n_action();
    for (const auto& layer : m.layers) {
      layer_offset.push_back(layer_memory);
      if (layer.kind == K::Delay) layer_memory += (long(layer.value) + 2) * na;
      else if (layer.kind == K::Lag || layer.kind == K::Play) layer_memory += na;
      else if (layer.kind == K::RunGain) layer_memory += 1;
      have_state_layers |= layer.kind == K::Noise || layer.kind == K::Quantise || layer.kind == K::Saturation;
    }
    trunk_out = m.window_features();
    for (const Dense& d : m.trunk)
      if (d.W.size()) trunk_out = d.W.rows();
    for (int i = 0; i < m.channels(); ++i) {
      centre.push_back((m.norm_high[size_t(i)] + m.norm_low[size_t(i)]) / 2);  // as Normaliser.centre/half
      half.push_back((m.norm_high[size_t(i)] - m.norm_low[size_t(i)]) / 2);
    }
    level.assign(size_t(m.n_state()), INFINITY);
    for (const auto& lim : m.residual.limits) level[size_t(lim.state)] = lim.level;
  }

  // A residual head's mean (n_state x count, in place): scale * head + base, the base each state's
  // last reading in the window `x` (column b at x + b * stride) that is not at its limit, its last
  // reading when every one is (EnvModel.residual_base).
  void add_base(float* mean, const float* x, long stride, int count) const {
    const int ns = m.n_state();
    const long c = m.channels(), last = m.history - 1;
    const float scale = m.residual.scale, tol = m.residual.tolerance;
    for (int b = 0; b < count; ++b) {
      const float* win = x + b * stride;
      float* mu = mean + long(b) * ns;
      for (int i = 0; i < ns; ++i) {
        long t = last;
        while (t >= 0 && !(std::abs(win[t * c + i] - level[size_t(i)]) > tol)) --t;
        mu[i] = scale * mu[i] + win[(t < 0 ? last : t) * c + i];
      }
    }
  }

  // The window of each run is kept twice over in a ring of 2l rows: row i and row i+l always hold
  // the same values, so the l rows starting at any p < l are contiguous and the model reads them in
  // place. A step writes one new row (at p and p+l) instead of shifting l-1 rows.
  void put_row(Workspace& w, int b, long pos, const double* v) {
    const long c = m.channels(), l = m.history;
    float* col = w.ring.col(b).data();
    for (long k = 0; k < c; ++k) {
      float z = float((v[k] - centre[size_t(k)]) / half[size_t(k)]);
      col[pos * c + k] = z;
      col[(pos + l) * c + k] = z;
    }
  }

  // A unit-variance draw of state i's step noise for run `run` at step t: normal, a two-scale normal
  // (k times the scale with probability p, the choice on uniform stream kMixStream | i), or a Student-t of
  // nu degrees of freedom as a normal over the root of a chi-square of nu further normals (keys
  // kDofStream | i << 8 | j), scaled by sqrt((nu - 2) / nu) (EnvModel.step_noise).
  double step_noise(uint64_t run, long t, int i) const {
    double z = normal(job.seed, run, uint32_t(t), uint32_t(i));
    if (!m.noise_mix.empty() && m.noise_mix[size_t(i)].first > 0) {
      const auto [p, k] = m.noise_mix[size_t(i)];
      const bool wide = uniform(job.seed, run, uint32_t(t), kMixStream | uint32_t(i)) < p;
      return z * (wide ? k : 1.0) / std::sqrt(1 - p + p * k * k);
    }
    const int nu = m.noise_dof.empty() ? 0 : m.noise_dof[size_t(i)];
    if (!nu) return z;
    double chi2 = 0;
    for (int j = 0; j < nu; ++j) {
      double g = normal(job.seed, run, uint32_t(t), kDofStream | uint32_t(i) << 8 | uint32_t(j));
      chi2 += g * g;
    }
    return z * std::sqrt((nu - 2) / chi2);
  }

  // Sets up run b's (global run `run`) layer memory from sigma_0's commands `window` (l rows of C
  // channels, the actions from channel n_state on), as LayerStack does from the window's actions.
  void layer_start(Workspace& w, int b, long run, const double* window) const {
    using K = Model::EffectLayer::Kind;
    const long na = m.n_action(), ns = m.n_state(), c = m.channels(), l = m.history;
    double* mem = w.layer_memory.data() + size_t(b) * size_t(layer_memory);
    for (size_t k = 0; k < m.layers.size(); ++k) {
      const auto& layer = m.layers[k];
      double* own = mem + layer_offset[k];
      if (layer.kind == K::Delay) {  // a ring of the last k+1 commands H_j at slot j mod (k+1), then H_0
        const long ring = long(layer.value) + 1;
        for (long j = std::max(0L, l - ring); j < l; ++j) std::copy_n(window + j * c + ns, na, own + (j % ring) * na);
        std::copy_n(window + ns, na, own + ring * na);
      } else if (layer.kind == K::Lag || layer.kind == K::Play) {
        std::copy_n(window + (l - 1) * c + ns, na, own);
      } else if (layer.kind == K::RunGain) {
        own[0] = 1 + layer.value * normal(job.seed, uint64_t(run), kRunGainStep, kLayerStream | uint32_t(k) << 16);
      }
    }
  }

  // What the controller and the log see of run b's predicted states `s` (written to `out`) at step t.
  void layer_states(const double* s, double* out, long run, long t) const {
    using K = Model::EffectLayer::Kind;
    const int ns = m.n_state();
    std::copy_n(s, ns, out);
    for (size_t k = 0; k < m.layers.size(); ++k) {
      const auto& layer = m.layers[k];
      const double v = layer.value;
      for (int i = 0; i < ns; ++i) {
        if (layer.kind == K::Noise)
          out[i] += v * normal(job.seed, uint64_t(run), uint32_t(t), kLayerStream | uint32_t(k) << 16 | uint32_t(i));
        else if (layer.kind == K::Quantise && v > 0)
          out[i] = std::nearbyint(out[i] / v) * v;
        else if (layer.kind == K::Saturation)
          out[i] = std::min(std::max(out[i], layer.low), layer.high);
      }
    }
    // what a sensor reports: within the declared range, at the resolution (envi_py.simulate.sensor_reading)
    for (int i = 0; i < ns && have_state_layers; ++i) {
      if (!std::isfinite(out[i]))
        throw std::invalid_argument("the effect layers " + m.describe_layers() + " drive state '" +
                                    m.states[size_t(i)].name + "' to a non-finite value");
      out[i] = std::min(std::max(out[i], m.states[size_t(i)].low), m.states[size_t(i)].high);
      if (!m.round_to.empty()) out[i] = std::nearbyint(out[i] / m.round_to[size_t(i)]) * m.round_to[size_t(i)];
    }
  }

  // What the model sees of run b's commands `a` (written to `out`) at step t (0-based).
  void layer_commands(Workspace& w, int b, const double* a, double* out, long t) const {
    using K = Model::EffectLayer::Kind;
    const long na = m.n_action(), l = m.history;
    double* mem = w.layer_memory.data() + size_t(b) * size_t(layer_memory);
    std::copy_n(a, na, out);
    for (size_t k = 0; k < m.layers.size(); ++k) {
      const auto& layer = m.layers[k];
      double* own = mem + layer_offset[k];
      const double v = layer.value;
      if (layer.kind == K::Delay) {
        const long ring = long(v) + 1, j = l + t, back = j - long(v);
        std::copy_n(out, na, own + (j % ring) * na);
        std::copy_n(back >= 0 ? own + (back % ring) * na : own + ring * na, na, out);
      } else if (layer.kind == K::Lag) {
        const double alpha = v <= 0 ? 1.0 : 1 - std::exp(-1 / v);
        for (long i = 0; i < na; ++i) out[i] = own[i] = own[i] + (out[i] - own[i]) * alpha;
      } else if (layer.kind == K::Play) {
        for (long i = 0; i < na; ++i) out[i] = own[i] = std::min(std::max(own[i], out[i] - v / 2), out[i] + v / 2);
      } else if (layer.kind == K::GainDrift) {
        const double gain = 1 + v * double(t + 1) / double(std::max(job.steps, 1L));
        for (long i = 0; i < na; ++i) out[i] *= gain;
      } else if (layer.kind == K::RunGain) {
        for (long i = 0; i < na; ++i) out[i] *= own[0];
      }
    }
  }

  // Each run's context bias (Model::context): context_W times the mean and population sd of every
  // state over sigma_0's l normalised rows (the ring's first l rows), as envi_py.dataset.context_of.
  void context_start(Workspace& w, int count) const {
    const long c = m.channels(), l = m.history, ns = m.n_state();
    Eigen::VectorXf ctx(2 * ns);
    for (int b = 0; b < count; ++b) {
      const float* col = w.ring.col(b).data();
      for (long i = 0; i < ns; ++i) {
        double sum = 0, sq = 0;
        for (long t = 0; t < l; ++t) sum += col[t * c + i];
        const double mu = sum / double(l);
        for (long t = 0; t < l; ++t) sq += (col[t * c + i] - mu) * (col[t * c + i] - mu);
        ctx[i] = float(mu);
        ctx[ns + i] = float(std::sqrt(sq / double(l)));
      }
      w.context_bias.col(b).noalias() = m.context_W * ctx;
    }
  }

  // The trunk's output for the window x: with a run context, its first (linear) layer, the context
  // bias added, then the rest (the first layer's activation first).
  const float* trunk(Workspace& w, const float* x, long in, long stride, int count) const {
    const Dense* layers = m.trunk.data();
    const Dense* end = layers + m.trunk.size();
    if (!m.context) return forward(layers, end, x, in, stride, count, w.buf[0].data(), w.buf[1].data(), w.scratch.data());
    float* h = const_cast<float*>(forward(layers, layers + 1, x, in, stride, count, w.buf[0].data(), w.buf[1].data(),
                                          w.scratch.data()));
    const long rows = m.context_W.rows();
    OutMap(h, rows, count) += w.context_bias.leftCols(count);
    return forward(layers + 1, end, h, rows, rows, count, w.buf[0].data(), w.buf[1].data(), w.scratch.data());
  }

  // As envi_py.controllers.in_range: a command outside its action channel's declared range is an error
  // naming the controller, the channel and the value (no actuator of the described system can do
  // it, and a log holding it could not be read back).
  void in_range(const double* actions, int count) const {
    const size_t na = m.actions.size();
    for (size_t i = 0; i < size_t(count) * na; ++i) {
      const ChannelInfo& ch = m.actions[i % na];
      if (!(actions[i] < ch.low || actions[i] > ch.high)) continue;  // NaN passes, as in Python
      char text[160];
      std::snprintf(text, sizeof text, " = %g, outside its declared range [%g, %g]", actions[i], ch.low, ch.high);
      throw std::invalid_argument("controller '" + ctrl.name() + "' commanded " + ch.name + text);
    }
  }

  void block(int thread, Workspace& w, long first, int count) {
    const int ns = m.n_state(), na = m.n_action(), c = m.channels();
    const long l = m.history;
    sink.begin(thread, first, count);
    ctrl.reset(w.memory.data(), count);
    for (long t = 0; t < l; ++t) {
      for (int b = 0; b < count; ++b) {
        const double* src = job.init + (size_t((first + b) / job.runs) * size_t(l) + size_t(t)) * size_t(c);
        std::copy(src, src + c, w.rows.data() + size_t(b) * size_t(c));
        put_row(w, b, t, src);
      }
      // warm-up: the controller sees sigma_0's states in order (answers discarded), so its memory
      // matches the real controller's when the closed loop starts
      ctrl.act(w.rows.data(), c, w.actions.data(), count, w.memory.data());
      sink.rows(thread, t, w.rows.data());
    }
    const bool layered = !m.layers.empty();
    if (layered)
      for (int b = 0; b < count; ++b)
        layer_start(w, b, first + b, job.init + size_t((first + b) / job.runs) * size_t(l) * size_t(c));
    if (m.context) context_start(w, count);
    const long in = m.window_features(), stride = w.ring.rows();
    long p = 0;
    for (long t = 0; t < job.steps; ++t) {
      const float* x = w.ring.data() + p * c;
      const float* h = m.trunk.empty() ? x : trunk(w, x, in, stride, count);
      const long hstride = m.trunk.empty() ? stride : trunk_out;
      const float* mu = forward(m.mean, h, trunk_out, hstride, count, w.buf[2].data(), w.buf[3].data(), w.scratch.data());
      if (m.gaussian() || !m.event.empty() || m.residual.on) {
        OutMap(w.mean.data(), ns, count) = Eigen::Map<const MatF>(mu, ns, count);
        mu = w.mean.data();
      }
      if (m.residual.on) add_base(w.mean.data(), x, stride, count);
      if (m.gaussian()) {
        const float* ls = forward(m.log_std, h, trunk_out, hstride, count, w.buf[2].data(), w.buf[3].data(),
                                 w.scratch.data());
        for (int b = 0; b < count; ++b)
          for (int i = 0; i < ns; ++i) {
            size_t k = size_t(b) * size_t(ns) + size_t(i);
            float eps = float(step_noise(uint64_t(first + b), t, i));
            w.mean.data()[k] += std::exp(ls[k]) * eps;
          }
      }
      const size_t ne = m.limit_events.size();
      if (ne) {  // a limit event happens with probability sigmoid(logit) (where likelier than not when deterministic)
        const float* lg = forward(m.event, h, trunk_out, hstride, count, w.buf[2].data(), w.buf[3].data(),
                                  w.scratch.data());
        for (int b = 0; b < count; ++b)
          for (size_t e = 0; e < ne; ++e) {
            double p = 1.0 / (1.0 + std::exp(-double(lg[size_t(b) * ne + e])));
            double u = m.gaussian() ? uniform(job.seed, uint64_t(first + b), uint32_t(t), uint32_t(e)) : 0.5;
            w.events[size_t(b) * ne + e] = u < p;
          }
      }
      for (int b = 0; b < count; ++b)
        for (int i = 0; i < ns; ++i) {
          size_t k = size_t(b) * size_t(ns) + size_t(i);
          double v = double(mu[k]) * half[size_t(i)] + centre[size_t(i)];
          if (m.clamp) v = std::min(std::max(v, m.limit_low[size_t(i)]), m.limit_high[size_t(i)]);
          if (!m.round_to.empty()) v = std::nearbyint(v / m.round_to[size_t(i)]) * m.round_to[size_t(i)];  // half to even, as np.round
          w.states[k] = v;
        }
      for (int b = 0; b < count; ++b)
        for (size_t e = 0; e < ne; ++e)
          if (w.events[size_t(b) * ne + e])
            w.states[size_t(b) * size_t(ns) + size_t(m.limit_events[e].state)] = m.limit_events[e].value;
      // with effect layers the controller and the log get the layered states, the model's window its
      // own prediction and the layered commands
      const double* seen = w.states.data();
      if (layered) {
        for (int b = 0; b < count; ++b)
          layer_states(w.states.data() + size_t(b) * size_t(ns), w.seen.data() + size_t(b) * size_t(ns), first + b, t);
        seen = w.seen.data();
      }
      ctrl.act(seen, ns, w.actions.data(), count, w.memory.data());
      in_range(w.actions.data(), count);
      for (int b = 0; b < count; ++b) {
        double* row = w.rows.data() + size_t(b) * size_t(c);
        std::copy_n(seen + size_t(b) * size_t(ns), ns, row);
        std::copy_n(w.actions.data() + size_t(b) * size_t(na), na, row + ns);
        if (layered) {
          double* view = w.view.data() + size_t(b) * size_t(c);
          std::copy_n(w.states.data() + size_t(b) * size_t(ns), ns, view);
          layer_commands(w, b, row + ns, view + ns, t);
          put_row(w, b, p, view);
        } else {
          put_row(w, b, p, row);
        }
      }
      sink.rows(thread, l + t, w.rows.data());
      p = (p + 1 == l) ? 0 : p + 1;
    }
    sink.end(thread);
  }
};

long total_runs(const Job& job) { return job.n_runs > 0 ? job.n_runs : job.windows * job.runs; }

// Runs per block from the job's size only, never from the thread count: a run's arithmetic then
// does not depend on how many threads share the work (GEMM rounding can depend on the block).
int block_size(const Job& job) {
  long n = job.windows * job.runs;
  long quarter = ((n + 3) / 4 + 7) / 8 * 8;  // at least four blocks for small jobs, so threads have work
  return int(std::max<long>(1, std::min<long>({long(job.block), std::max<long>(64, quarter), n})));
}

}  // namespace

Plan plan(const Job& job) {
  int t = job.threads > 0 ? job.threads : int(std::max(1u, std::thread::hardware_concurrency()));
  t = int(std::max<long>(1, std::min<long>(t, total_runs(job))));
  return {t, block_size(job)};
}

void simulate(const Model& model, const Controller& controller, const Job& job, Sink& sink) {
  controller.check(model.n_state(), model.n_action());
  if (!job.init || job.windows < 1) throw std::invalid_argument("no initial windows");
  if (job.runs < 1) throw std::invalid_argument("runs must be at least 1");
  if (job.steps < 0 || job.steps > (long(1) << 32)) throw std::invalid_argument("steps out of range");
  if (job.block < 1) throw std::invalid_argument("block must be at least 1");
  long n = total_runs(job);
  if (job.first_run < 0 || job.first_run + n > job.windows * job.runs)
    throw std::invalid_argument("run range exceeds windows x runs");
  const auto [threads, block] = plan(job);
  const long blocks = (n + block - 1) / block;
  Runner runner(model, controller, job, sink);
  std::atomic<long> next{0};
  std::exception_ptr error;
  std::mutex error_mutex;
  auto work = [&](int thread) {
    try {
      Workspace w(model, controller, block, runner.layer_memory);  // every buffer of this thread, allocated once
      for (long k; (k = next.fetch_add(1)) < blocks;) {
        long first = job.first_run + k * block;
        runner.block(thread, w, first, int(std::min<long>(block, job.first_run + n - first)));
      }
    } catch (...) {
      std::lock_guard<std::mutex> lock(error_mutex);
      if (!error) error = std::current_exception();
      next = blocks;  // stop the other workers at their next block
    }
  };
  if (threads == 1) {
    work(0);
  } else {
    std::vector<std::thread> pool;
    for (int i = 0; i < threads; ++i) pool.emplace_back(work, i);
    for (auto& th : pool) th.join();
  }
  if (error) std::rethrow_exception(error);
}

}  // namespace envi
