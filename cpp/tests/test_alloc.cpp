// Zero heap allocations inside the step loop: every allocation is counted per thread, and a sink
// checks that none happened between two rows of the same block.
#include <atomic>
#include <cstdlib>
#include <vector>

#include "check.hpp"
#include "envi/engine.hpp"
#include "onnx_builder.hpp"

// Counting operator new would miss Eigen, which allocates with malloc; interposing malloc itself
// counts both (the default operator new calls malloc). glibc exports its allocator as __libc_*.
static thread_local long t_allocs = 0;

extern "C" {
void* __libc_malloc(std::size_t);
void* __libc_calloc(std::size_t, std::size_t);
void* __libc_realloc(void*, std::size_t);
void* __libc_memalign(std::size_t, std::size_t);
void __libc_free(void*);

void* malloc(std::size_t n) { ++t_allocs; return __libc_malloc(n); }
void* calloc(std::size_t n, std::size_t k) { ++t_allocs; return __libc_calloc(n, k); }
void* realloc(void* p, std::size_t n) { ++t_allocs; return __libc_realloc(p, n); }
void free(void* p) { __libc_free(p); }
void* memalign(std::size_t a, std::size_t n) { ++t_allocs; return __libc_memalign(a, n); }
void* aligned_alloc(std::size_t a, std::size_t n) { ++t_allocs; return __libc_memalign(a, n); }
int posix_memalign(void** out, std::size_t a, std::size_t n) {
  ++t_allocs;
  *out = __libc_memalign(a, n);
  return *out ? 0 : 12;  // ENOMEM
}
}

struct Watch : envi::Sink {
  std::vector<long> last;
  std::atomic<long> steps_seen{0}, allocating_steps{0};
  explicit Watch(int threads) : last(size_t(threads), -1) {}
  void begin(int th, long, int) override { last[size_t(th)] = -1; }
  void rows(int th, long t, const double*) override {
    if (t < 5) return;  // the initial window rows are set up before the loop
    if (last[size_t(th)] >= 0) {
      ++steps_seen;
      if (t_allocs != last[size_t(th)]) ++allocating_steps;
    }
    last[size_t(th)] = t_allocs;
  }
  void end(int) override {}
};

int main() {
  pb::Spec spec;
  spec.history = 5;
  spec.hidden = 256;  // the paper's width: large enough for Eigen's blocked GEMM path
  for (bool gaussian : {false, true}) {
    spec.gaussian = gaussian;
    pb::Bytes bytes = pb::model(spec);
    envi::Model m = envi::load_model(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size());
    std::vector<double> init(5 * 2, 40.0);
    for (const char* c : {R"({"name": "lane-keeping"})", R"({"name": "pid", "params": {"ki": 1}})"})
      for (int threads : {1, 2}) {
        envi::Job job;
        job.init = init.data();
        job.windows = 1;
        job.runs = 1000;
        job.steps = 20;
        job.threads = threads;
        job.block = 512;
        Watch w(envi::plan(job).threads);
        envi::simulate(m, envi::Controller::parse(c), job, w);
        CHECK(w.steps_seen > 0);
        CHECK(w.allocating_steps == 0);
        std::printf("gaussian=%d %s threads=%d: %ld steps watched, %ld allocated\n", gaussian, c, threads,
                    long(w.steps_seen), long(w.allocating_steps));
      }
  }
  // two states, two actions, a combine of a PID and a bang-bang: still no allocation per step, with
  // a residual mean head whose second state has a limit event too
  spec.gaussian = true;
  spec.n_state = spec.n_action = 2;
  for (bool residual : {false, true}) {
    spec.residual = residual;
    spec.limit_state = residual ? 1 : -1;
    pb::Bytes bytes = pb::model(spec);
    envi::Model m = envi::load_model(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size());
    CHECK(m.residual.on == residual);
    std::vector<double> init(5 * 4, 40.0);
    envi::Job job;
    job.init = init.data();
    job.windows = 1;
    job.runs = 600;
    job.steps = 20;
    job.threads = 2;
    job.block = 256;
    Watch w(envi::plan(job).threads);
    envi::simulate(m, envi::Controller::parse(R"({"name": "combine", "params": {"loops": [)"
                                              R"({"name": "pid", "params": {"ki": 1, "kd": 0.1, "input": 1}}, {"name": "bang-bang"}]}})"),
                   job, w);
    CHECK(w.steps_seen > 0);
    CHECK(w.allocating_steps == 0);
    std::printf("2 states/2 actions, combine, residual=%d: %ld steps watched, %ld allocated\n", residual,
                long(w.steps_seen), long(w.allocating_steps));
  }
  std::printf("test_alloc: %d failure(s)\n", failures());
  return failures() ? 1 : 0;
}
