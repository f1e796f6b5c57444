// The eight driving-quality metrics of envi_py/metrics.py::driving_metrics, computed one sample at
// a time so a simulation can be scored while it runs, without keeping its trace.
#pragma once
#include <string>
#include <vector>

#include "envi/engine.hpp"

namespace envi {

struct MetricConfig {
  double centre = 40.0, band = 10.0;
  long skip = 10;   // rows not scored (sigma_0)
  int channel = 0;  // scored column of a row (states first)
};

extern const char* const kMetricNames[8];

// Episodes of one run: feed the scored samples in order, then read the eight metrics.
class EpisodeCounter {
 public:
  void reset() { *this = EpisodeCounter(); }
  void add(double c, const MetricConfig& cfg);
  void finish(double out[8]);  // steady_count, steady_duration, over_count, over_amplitude, ...

 private:
  int region_ = -1;  // 0 steady, 1 over, 2 under
  double epmax_ = 0.0;
  double count_[3] = {0, 0, 0}, duration_[3] = {0, 0, 0}, amplitude_[3] = {0, 0, 0};
  void close();
};

// (runs, T) traces -> (runs, 8); throws std::invalid_argument when nothing is left after the skip.
void driving_metrics(const double* traces, long runs, long length, const MetricConfig& cfg, double* out);

// Scores every run as the engine produces it; `emit(first_run, count, metrics count x 8)` is called
// at the end of each block (from the worker thread: make it thread-safe).
class MetricsSink : public Sink {
 public:
  using Emit = void (*)(void* ctx, long first_run, int count, const double* metrics);
  MetricsSink(const MetricConfig& cfg, int channels, int threads, int block, Emit emit, void* ctx);
  void begin(int thread, long first_run, int count) override;
  void rows(int thread, long t, const double* values) override;
  void end(int thread) override;

 private:
  struct PerThread {
    long first = 0;
    int count = 0;
    std::vector<EpisodeCounter> runs;
    std::vector<double> out;
  };
  MetricConfig cfg_;
  int channels_;
  std::vector<PerThread> threads_;
  Emit emit_;
  void* ctx_;
};

}  // namespace envi
