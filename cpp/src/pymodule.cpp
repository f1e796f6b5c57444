// envi_py._native: the engine for Python. Arrays come in and go out without copies (float64,
// C order; anything else is converted once), and the GIL is released while the engine runs.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cstring>
#include <mutex>

#include "envi/controller.hpp"
#include "envi/engine.hpp"
#include "envi/ensemble.hpp"
#include "envi/metrics.hpp"
#include "envi/model.hpp"
#include "envi/peak.hpp"
#include "envi/sha256.hpp"

namespace py = pybind11;
using namespace envi;

namespace {

using ArrayD = py::array_t<double, py::array::c_style | py::array::forcecast>;

// Writes every row straight into the (runs, history + steps, channels) output array.
class TraceSink : public Sink {
 public:
  TraceSink(double* out, long length, int channels, long first_run, int threads)
      : out_(out), length_(length), channels_(channels), first_run_(first_run), blocks_(size_t(threads)) {}
  void begin(int thread, long first, int count) override { blocks_[size_t(thread)] = {first - first_run_, count}; }
  void rows(int thread, long t, const double* values) override {
    auto [first, count] = blocks_[size_t(thread)];
    for (int b = 0; b < count; ++b)
      std::memcpy(out_ + ((first + b) * length_ + t) * channels_, values + size_t(b) * size_t(channels_),
                  sizeof(double) * size_t(channels_));
  }
  void end(int) override {}

 private:
  double* out_;
  long length_;
  int channels_;
  long first_run_;
  std::vector<std::pair<long, int>> blocks_;
};

Job make_job(const Model& m, const ArrayD& init, long steps, long runs, uint64_t seed, int threads, int block) {
  if (init.ndim() != 3 || init.shape(1) != m.history || init.shape(2) != m.channels())
    throw std::invalid_argument("initial windows must be (K, " + std::to_string(m.history) + ", " +
                                std::to_string(m.channels()) + ") for this model");
  if (steps < 0) throw std::invalid_argument("steps must not be negative");
  Job job;
  job.init = init.data();
  job.windows = long(init.shape(0));
  job.runs = runs;
  job.steps = steps;
  job.seed = seed;
  job.threads = threads;
  job.block = block;
  return job;
}

py::array_t<double> rollout(const Model& m, const std::string& controller, const ArrayD& init, long steps, long runs,
                            uint64_t seed, int threads, int block) {
  Controller ctrl = Controller::parse(controller, m.period_ms);
  ctrl.check(m.n_state(), m.n_action());
  Job job = make_job(m, init, steps, runs, seed, threads, block);
  long total = job.windows * runs, length = m.history + steps;
  py::array_t<double> out({py::ssize_t(total), py::ssize_t(length), py::ssize_t(m.channels())});
  if (total == 0) return out;
  double* dst = out.mutable_data();
  {
    py::gil_scoped_release nogil;
    TraceSink sink(dst, length, m.channels(), 0, plan(job).threads);
    simulate(m, ctrl, job, sink);
  }
  return out;
}

py::array_t<double> rollout_metrics(const Model& m, const std::string& controller, const ArrayD& init, long steps,
                                    long runs, uint64_t seed, int threads, int block, double centre, double band,
                                    long skip, int channel) {
  Controller ctrl = Controller::parse(controller, m.period_ms);
  ctrl.check(m.n_state(), m.n_action());
  Job job = make_job(m, init, steps, runs, seed, threads, block);
  MetricConfig cfg{centre, band, skip, channel};
  if (m.history + steps - skip <= 0) throw std::invalid_argument("nothing left to score after skipping " + std::to_string(skip) + " rows");
  long total = job.windows * runs;
  py::array_t<double> out({py::ssize_t(total), py::ssize_t(8)});
  double* dst = out.mutable_data();
  {
    py::gil_scoped_release nogil;
    Plan p = plan(job);
    auto emit = [](void* ctx, long first, int count, const double* metrics) {
      std::memcpy(static_cast<double*>(ctx) + first * 8, metrics, sizeof(double) * 8 * size_t(count));
    };
    MetricsSink sink(cfg, m.channels(), p.threads, p.block, emit, dst);
    simulate(m, ctrl, job, sink);
  }
  return out;
}

// A controller alone over given state sequences, as the simulator drives it: reset, warm-up on the
// first `history` rows of each run (answers discarded), then one call per remaining row.
py::array_t<double> controller_actions(const std::string& spec, const ArrayD& states, long history, int n_action,
                                       double period_ms) {
  if (states.ndim() != 3) throw std::invalid_argument("states must be (N, T, n_state)");
  const long N = long(states.shape(0)), T = long(states.shape(1));
  const int ns = int(states.shape(2));
  if (history < 0 || history > T) throw std::invalid_argument("history must be within 0 .. T");
  Controller c = Controller::parse(spec, period_ms);
  c.check(ns, n_action);
  py::array_t<double> out({py::ssize_t(N), py::ssize_t(T - history), py::ssize_t(n_action)});
  std::vector<double> memory(size_t(N) * size_t(c.memory_per_run())), row(size_t(N) * size_t(ns)),
      actions(size_t(N) * size_t(n_action));
  c.reset(memory.data(), int(N));
  const double* src = states.data();
  double* dst = out.mutable_data();
  for (long t = 0; t < T; ++t) {
    for (long b = 0; b < N; ++b) std::copy_n(src + (b * T + t) * ns, ns, row.data() + b * ns);
    c.act(row.data(), ns, actions.data(), int(N), memory.data());
    if (t >= history)
      for (long b = 0; b < N; ++b)
        std::copy_n(actions.data() + b * n_action, n_action, dst + (b * (T - history) + t - history) * n_action);
  }
  return out;
}

}  // namespace

#ifndef ENVI_MODULE_NAME
#define ENVI_MODULE_NAME _native
#endif
PYBIND11_MODULE(ENVI_MODULE_NAME, mod) {
  mod.doc() = "envi native runtime: ONNX environment models in closed loop with controllers";
  py::register_exception<ModelError>(mod, "ModelError", PyExc_ValueError);
  // Python's envi_py.controllers.WidthError is a ValueError too; tests match on the message.
  py::register_exception<WidthError>(mod, "WidthError", PyExc_ValueError);

  py::class_<Model>(mod, "Model")
      .def(py::init([](py::bytes data) {
             std::string s = data;  // one copy of the file; the weights are compiled out of it
             py::gil_scoped_release nogil;
             return load_model(reinterpret_cast<const uint8_t*>(s.data()), s.size());
           }),
           py::arg("onnx_bytes"))
      .def_readonly("history", &Model::history)
      // A PID's default period (ms); from the file's envi.period_ms, 0 when unknown (then 40 ms).
      // Writable so a checkpoint's resolved period travels with the model compiled from it.
      .def_readwrite("period_ms", &Model::period_ms)
      .def_property_readonly("n_state", &Model::n_state)
      .def_property_readonly("n_action", &Model::n_action)
      .def_property_readonly("gaussian", &Model::gaussian)
      .def_property_readonly("residual", [](const Model& m) { return m.residual.on; })
      .def_readonly("metadata", &Model::metadata)
      .def_property_readonly("layers", [](const Model& m) {
        py::list out;
        for (const auto* part : {&m.trunk, &m.mean, &m.log_std, &m.event})
          for (const Dense& d : *part) out.append(py::make_tuple(d.W.rows(), d.W.cols(), int(d.act)));
        return out;
      });

  mod.def("rollout", &rollout, py::arg("model"), py::arg("controller"), py::arg("init"), py::arg("steps"),
          py::arg("runs") = 1, py::arg("seed") = 0, py::arg("threads") = 0, py::arg("block") = 256,
          "Closed-loop runs: init (K, l, C) physical -> (K*runs, l+steps, C).");
  mod.def("rollout_metrics", &rollout_metrics, py::arg("model"), py::arg("controller"), py::arg("init"),
          py::arg("steps"), py::arg("runs") = 1, py::arg("seed") = 0, py::arg("threads") = 0, py::arg("block") = 256,
          py::arg("centre") = 40.0, py::arg("band") = 10.0, py::arg("skip") = 10, py::arg("channel") = 0,
          "Closed-loop runs scored on the fly: (K*runs, 8) driving metrics, no traces kept.");
  mod.def("controller_actions", &controller_actions, py::arg("spec"), py::arg("states"), py::arg("history"),
          py::arg("n_action"), py::arg("period_ms") = 0.0,
          "A controller alone: states (N, T, n_state) -> actions (N, T - history, n_action) after a reset "
          "and a warm-up on the first `history` rows; period_ms is a PID's default period (0: 40 ms).");
  mod.def("driving_metrics",
          [](const ArrayD& traces, double centre, double band, long skip) {
            if (traces.ndim() != 2) throw std::invalid_argument("traces must be (runs, T)");
            py::array_t<double> out({traces.shape(0), py::ssize_t(8)});
            driving_metrics(traces.data(), long(traces.shape(0)), long(traces.shape(1)), MetricConfig{centre, band, skip, 0},
                            out.mutable_data());
            return out;
          },
          py::arg("traces"), py::arg("centre") = 40.0, py::arg("band") = 10.0, py::arg("skip") = 10);
  mod.def("peak_flops",
          [](int threads, double seconds) {
            py::gil_scoped_release nogil;
            return peak_flops(threads, seconds);
          },
          py::arg("threads") = 0, py::arg("seconds") = 0.5,
          "FLOP/s of register-only fused multiply-adds on this build's widest vectors (a benchmark's ceiling).");
  mod.def("sha256_hex",
          [](py::bytes data) {
            std::string s = data;
            return sha256_hex(s.data(), s.size());
          },
          py::arg("data"), "SHA-256 of bytes as hex: the engine's own implementation, checked against hashlib.");
  mod.def("content_sha256",
          [](py::bytes data) {
            std::string s = data;
            return content_sha256(reinterpret_cast<const uint8_t*>(s.data()), s.size());
          },
          py::arg("onnx_bytes"), "The content hash of an ONNX file as the loader computes it (envi.content_sha256).");
  mod.def("members_of_runs", &members_of_runs, py::arg("members"), py::arg("batch"), py::arg("seed"),
          "Which member of a seed ensemble simulates each run, as envi_sim shares them out (the twin of "
          "envi_py.simulate.members_of_runs).");
  mod.def("simd", [] { return std::string(Eigen::SimdInstructionSetsInUse()); },
          "Vector instruction sets this build of the engine uses.");
}
