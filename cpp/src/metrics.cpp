#include "envi/metrics.hpp"

#include <algorithm>
#include <stdexcept>

namespace envi {

const char* const kMetricNames[8] = {"steady_count", "steady_duration", "over_count", "over_amplitude",
                                     "over_duration", "under_count", "under_amplitude", "under_duration"};

void EpisodeCounter::close() {
  if (region_ >= 0) amplitude_[region_] += epmax_;
}

void EpisodeCounter::add(double c, const MetricConfig& cfg) {
  const double upper = cfg.centre + cfg.band, lower = cfg.centre - cfg.band;
  int r = c > upper ? 1 : c < lower ? 2 : 0;  // NaN compares false: steady, as in numpy
  double excursion = r == 1 ? c - upper : r == 2 ? lower - c : 0.0;
  if (r != region_) {
    close();
    region_ = r;
    count_[r] += 1;
    epmax_ = 0.0;  // numpy starts each episode's maximum at 0
  }
  duration_[r] += 1;
  epmax_ = std::max(epmax_, excursion);
}

void EpisodeCounter::finish(double out[8]) {
  close();
  region_ = -1;
  const double v[8] = {count_[0], duration_[0], count_[1], amplitude_[1], duration_[1],
                       count_[2], amplitude_[2], duration_[2]};
  std::copy(v, v + 8, out);
}

void driving_metrics(const double* traces, long runs, long length, const MetricConfig& cfg, double* out) {
  if (length - cfg.skip <= 0)
    throw std::invalid_argument("runs of " + std::to_string(length) + " rows leave nothing to score after skipping " +
                                std::to_string(cfg.skip));
  for (long r = 0; r < runs; ++r) {
    EpisodeCounter e;
    for (long t = std::max<long>(cfg.skip, 0); t < length; ++t) e.add(traces[r * length + t], cfg);
    e.finish(out + r * 8);
  }
}

MetricsSink::MetricsSink(const MetricConfig& cfg, int channels, int threads, int block, Emit emit, void* ctx)
    : cfg_(cfg), channels_(channels), threads_(size_t(threads)), emit_(emit), ctx_(ctx) {
  if (cfg.channel < 0 || cfg.channel >= channels) throw std::invalid_argument("metric channel out of range");
  for (auto& t : threads_) {
    t.runs.resize(size_t(block));
    t.out.resize(size_t(block) * 8);
  }
}

void MetricsSink::begin(int thread, long first_run, int count) {
  PerThread& t = threads_[size_t(thread)];
  t.first = first_run;
  t.count = count;
  for (int b = 0; b < count; ++b) t.runs[size_t(b)].reset();
}

void MetricsSink::rows(int thread, long step, const double* values) {
  if (step < cfg_.skip) return;
  PerThread& t = threads_[size_t(thread)];
  for (int b = 0; b < t.count; ++b) t.runs[size_t(b)].add(values[size_t(b) * size_t(channels_) + size_t(cfg_.channel)], cfg_);
}

void MetricsSink::end(int thread) {
  PerThread& t = threads_[size_t(thread)];
  for (int b = 0; b < t.count; ++b) t.runs[size_t(b)].finish(t.out.data() + size_t(b) * 8);
  emit_(ctx_, t.first, t.count, t.out.data());
}

}  // namespace envi
