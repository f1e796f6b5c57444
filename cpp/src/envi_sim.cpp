// envi_sim: closed-loop simulation from the command line, without Python.
//
//   envi_sim --model m.onnx --init log_30_0.csv [more.csv ...] --controller '{"name": "lane-keeping",
//            "params": {"x": 30}}' --runs 100 --steps 500 [--seed 0] [--threads 0]
//            [--out DIR] [--metrics FILE|-] [--metrics-only] [--centre 40] [--band 10] [--skip l]
//
// Runs are simulated in chunks; each chunk's logs and metric rows are written before the next
// starts, so memory stays flat however many runs are asked for (with --metrics-only nothing but
// the running metric sums outlives a block).
#include <cstdio>
#include <cstring>
#include <fstream>
#include <iostream>
#include <memory>
#include <mutex>
#include <sstream>
#include <sys/stat.h>

#include "envi/controller.hpp"
#include "envi/csvlog.hpp"
#include "envi/engine.hpp"
#include "envi/json.hpp"
#include "envi/metrics.hpp"
#include "envi/model.hpp"

using namespace envi;

namespace {

const char* kUsage =
    "usage: envi_sim --model MODEL.onnx --init LOG.csv [LOG.csv ...] --controller JSON|@FILE\n"
    "                --steps T [--runs N] [--seed S] [--threads K] [--block B]\n"
    "                [--out DIR] [--metrics FILE|-] [--metrics-only]\n"
    "                [--centre 40] [--band 10] [--skip HISTORY]\n";

struct Args {
  std::string model, controller, out, metrics;
  std::vector<std::string> init;
  long steps = -1, runs = 1, skip = -1;
  uint64_t seed = 0;
  int threads = 0, block = 256;
  double centre = 40.0, band = 10.0;
  bool metrics_only = false;
};

long to_long(const std::string& flag, const std::string& v) {
  char* end = nullptr;
  long x = std::strtol(v.c_str(), &end, 10);
  if (v.empty() || *end) throw std::invalid_argument(flag + ": not an integer: " + v);
  return x;
}

double to_double(const std::string& flag, const std::string& v) {
  char* end = nullptr;
  double x = std::strtod(v.c_str(), &end);
  if (v.empty() || *end) throw std::invalid_argument(flag + ": not a number: " + v);
  return x;
}

Args parse(int argc, char** argv) {
  Args a;
  for (int i = 1; i < argc; ++i) {
    std::string f = argv[i];
    auto val = [&]() -> std::string {
      if (i + 1 >= argc) throw std::invalid_argument(f + " needs a value");
      return argv[++i];
    };
    if (f == "--model") a.model = val();
    else if (f == "--init") {
      a.init.push_back(val());
      while (i + 1 < argc && std::strncmp(argv[i + 1], "--", 2) != 0) a.init.push_back(argv[++i]);
    }
    else if (f == "--controller") a.controller = val();
    else if (f == "--steps") a.steps = to_long(f, val());
    else if (f == "--runs") a.runs = to_long(f, val());
    else if (f == "--seed") a.seed = uint64_t(to_long(f, val()));
    else if (f == "--threads") a.threads = int(to_long(f, val()));
    else if (f == "--block") a.block = int(to_long(f, val()));
    else if (f == "--out") a.out = val();
    else if (f == "--metrics") a.metrics = val();
    else if (f == "--metrics-only") a.metrics_only = true;
    else if (f == "--centre") a.centre = to_double(f, val());
    else if (f == "--band") a.band = to_double(f, val());
    else if (f == "--skip") a.skip = to_long(f, val());
    else if (f == "-h" || f == "--help") { std::cout << kUsage; std::exit(0); }
    else throw std::invalid_argument("unknown option " + f);
  }
  if (a.model.empty() || a.init.empty() || a.controller.empty() || a.steps < 0)
    throw std::invalid_argument("--model, --init, --controller and --steps are required");
  if (a.runs < 1) throw std::invalid_argument("--runs must be at least 1");
  if (a.metrics_only && a.metrics.empty()) throw std::invalid_argument("--metrics-only needs --metrics FILE (or -)");
  if (!a.metrics_only && a.out.empty() && a.metrics.empty()) throw std::invalid_argument("nothing to write: give --out and/or --metrics");
  if (!a.controller.empty() && a.controller[0] == '@') {
    std::ifstream in(a.controller.substr(1));
    if (!in) throw std::invalid_argument("cannot read controller file " + a.controller.substr(1));
    std::stringstream ss;
    ss << in.rdbuf();
    a.controller = ss.str();
  }
  return a;
}

Json num(double v, bool integer = false) {
  Json j;
  j.type = Json::Type::Number;
  j.number = v;
  j.integer = integer;
  return j;
}
Json str(const std::string& s) {
  Json j;
  j.type = Json::Type::String;
  j.string = s;
  return j;
}
Json obj(std::vector<std::pair<std::string, Json>> kv) {
  Json j;
  j.type = Json::Type::Object;
  j.object = std::move(kv);
  return j;
}

std::string metadata(const Model& m, const std::string& key) {
  for (const auto& kv : m.metadata)
    if (kv.first == key) return kv.second;
  return "null";
}

// Forwards every row to a chunk's trace buffer and/or the metrics.
class ChunkSink : public Sink {
 public:
  ChunkSink(double* traces, long length, int channels, long chunk_first, int threads, MetricsSink* metrics)
      : traces_(traces), length_(length), channels_(channels), chunk_first_(chunk_first), blocks_(size_t(threads)), metrics_(metrics) {}
  void begin(int thread, long first, int count) override {
    blocks_[size_t(thread)] = {first - chunk_first_, count};
    if (metrics_) metrics_->begin(thread, first, count);
  }
  void rows(int thread, long t, const double* v) override {
    if (traces_) {
      auto [first, count] = blocks_[size_t(thread)];
      for (int b = 0; b < count; ++b)
        std::memcpy(traces_ + ((first + b) * length_ + t) * channels_, v + size_t(b) * size_t(channels_), sizeof(double) * size_t(channels_));
    }
    if (metrics_) metrics_->rows(thread, t, v);
  }
  void end(int thread) override {
    if (metrics_) metrics_->end(thread);
  }

 private:
  double* traces_;
  long length_;
  int channels_;
  long chunk_first_;
  std::vector<std::pair<long, int>> blocks_;
  MetricsSink* metrics_;
};

struct MetricRows {
  std::vector<double> rows;  // chunk x 8
  long chunk_first = 0;
};

int run(const Args& a) {
  Model m = load_model_file(a.model);
  Controller ctrl = Controller::parse(a.controller, m.period_ms);
  Json ctrl_in = Json::parse(a.controller);
  const Json* params = ctrl_in.find("params");
  Json ctrl_json = obj({{"name", ctrl_in.at("name")}, {"params", params && !params->is_null() ? *params : obj({})}});

  const long l = m.history, c = m.channels(), length = l + a.steps;
  std::vector<InitialWindow> windows;
  std::vector<double> init;
  for (const auto& p : a.init) {
    windows.push_back(read_initial_window(p, m));
    init.insert(init.end(), windows.back().values.begin(), windows.back().values.end());
  }
  const long K = long(windows.size()), R = K * a.runs;
  MetricConfig mcfg{a.centre, a.band, a.skip >= 0 ? a.skip : l, 0};
  const bool want_logs = !a.metrics_only && !a.out.empty(), want_metrics = !a.metrics.empty();
  if (want_metrics && length - mcfg.skip <= 0) throw std::invalid_argument("nothing left to score after --skip rows");
  if (want_logs) ::mkdir(a.out.c_str(), 0777);

  Job job;
  job.init = init.data();
  job.windows = K;
  job.runs = a.runs;
  job.steps = a.steps;
  job.seed = a.seed;
  job.threads = a.threads;
  job.block = a.block;
  const Plan full = plan(job);
  // Chunk: a whole number of blocks (so block boundaries, hence results, do not depend on it),
  // enough to keep every thread busy; logs bound it by memory (~64 MB of traces).
  long blocks_per_chunk = 16;
  if (want_logs) blocks_per_chunk = std::max<long>(1, std::min<long>(16, (long(8) << 20) / std::max<long>(1, length * c * full.block)));
  const long chunk = blocks_per_chunk * full.block;

  std::ofstream metrics_file;
  std::ostream* mout = nullptr;
  if (want_metrics) {
    if (a.metrics == "-") mout = &std::cout;
    else {
      metrics_file.open(a.metrics);
      if (!metrics_file) throw std::runtime_error(a.metrics + ": cannot write");
      mout = &metrics_file;
    }
    *mout << "{\"metrics\": [";
    for (int k = 0; k < 8; ++k) *mout << (k ? ", " : "") << '"' << kMetricNames[k] << '"';
    *mout << "], \"config\": {\"centre\": " << py_float(mcfg.centre) << ", \"band\": " << py_float(mcfg.band)
          << ", \"skip\": " << mcfg.skip << ", \"channel\": " << mcfg.channel << "}, \"model\": " << json_quote(a.model)
          << ", \"controller\": " << ctrl.to_json() << ", \"windows\": " << K << ", \"runs_per_window\": " << a.runs
          << ", \"steps\": " << a.steps << ", \"seed\": " << a.seed << ",\n\"per_run\": [";
  }
  std::vector<double> sums(8, 0.0), traces;
  MetricRows mrows;
  std::mutex mutex;
  const std::string schema = metadata(m, "envi.schema");
  Json schema_json = Json::parse(schema);
  for (long first = 0; first < R; first += chunk) {
    Job part = job;
    part.first_run = first;
    part.n_runs = std::min(chunk, R - first);
    Plan p = plan(part);
    if (want_logs) traces.assign(size_t(part.n_runs) * size_t(length) * size_t(c), 0.0);
    mrows.rows.assign(size_t(part.n_runs) * 8, 0.0);
    mrows.chunk_first = first;
    std::unique_ptr<MetricsSink> ms;
    if (want_metrics)
      ms = std::make_unique<MetricsSink>(mcfg, int(c), p.threads, p.block, [](void* ctx, long f, int n, const double* v) {
        auto* r = static_cast<MetricRows*>(ctx);
        std::memcpy(r->rows.data() + (f - r->chunk_first) * 8, v, sizeof(double) * 8 * size_t(n));
      }, &mrows);
    ChunkSink sink(want_logs ? traces.data() : nullptr, length, int(c), first, p.threads, ms.get());
    simulate(m, ctrl, part, sink);
    for (long i = 0; i < part.n_runs; ++i) {
      long g = first + i, k = g / a.runs, r = g % a.runs;
      if (want_metrics) {
        *mout << (g ? ",\n[" : "\n[");
        for (int j = 0; j < 8; ++j) {
          double v = mrows.rows[size_t(i) * 8 + size_t(j)];
          sums[size_t(j)] += v;
          *mout << (j ? ", " : "") << py_float(v);
        }
        *mout << "]";
      }
      if (want_logs) {
        const InitialWindow& w = windows[size_t(k)];
        double period = l > 1 ? median_period(w.time) : (m.period_ms > 0 ? m.period_ms : 40.0);
        std::vector<double> time(w.time);
        for (long t = 1; t <= a.steps; ++t) time.push_back(w.time.back() + period * double(t));
        std::string run_id = w.run_id + "-sim" + std::to_string(r);
        Json meta = obj({{"schema_version", num(1, true)},
                         {"states", schema_json.at("states")},
                         {"actions", schema_json.at("actions")},
                         {"controller", ctrl_json},
                         {"period_ms", num(period)},
                         {"run_id", str(run_id)},
                         {"source", str("sim")},
                         {"provenance", obj({{"init_log", str(w.name)},
                                             {"model_algorithm", str(m.algorithm)},
                                             {"seed", num(double(a.seed), true)},
                                             {"replicate", num(double(r), true)}})}});
        write_log(a.out, run_id, m, meta, time, traces.data() + size_t(i) * size_t(length) * size_t(c), length);
      }
    }
  }
  if (want_metrics) {
    *mout << "],\n\"mean\": [";
    for (int j = 0; j < 8; ++j) *mout << (j ? ", " : "") << py_float(sums[size_t(j)] / double(R));
    *mout << "]}\n";
    mout->flush();
    if (!*mout) throw std::runtime_error(a.metrics + ": write failed");
  }
  if (mout != &std::cout)
    std::cerr << "envi_sim: " << R << " runs x " << a.steps << " steps (" << full.threads << " threads)\n";
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return run(parse(argc, argv));
  } catch (const std::invalid_argument& e) {
    std::cerr << "envi_sim: " << e.what() << "\n" << kUsage;
    return 2;
  } catch (const std::exception& e) {
    std::cerr << "envi_sim: " << e.what() << "\n";
    return 1;
  }
}
