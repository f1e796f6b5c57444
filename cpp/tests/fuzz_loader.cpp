// Fuzz harness: loads every file named on the command line; a file that loads is also simulated
// for a few steps. Rejection must be a ModelError; anything else (another exception, or a report
// from AddressSanitizer/UBSan, with which tests/fuzz_loader_test.py builds this) is a finding.
#include <cstdio>
#include <fstream>
#include <iterator>
#include <vector>

#include "envi/engine.hpp"
#include "envi/model.hpp"

struct Discard : envi::Sink {
  double sum = 0;
  int channels;
  explicit Discard(int c) : channels(c) {}
  void begin(int, long, int) override {}
  void rows(int, long, const double* v) override { sum += v[0]; }
  void end(int) override {}
};

int main(int argc, char** argv) {
  long loaded = 0, rejected = 0;
  for (int i = 1; i < argc; ++i) {
    std::ifstream in(argv[i], std::ios::binary);
    std::vector<uint8_t> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    try {
      envi::Model m = envi::load_model(bytes.data(), bytes.size());
      std::vector<double> init(size_t(m.history) * size_t(m.channels()), 40.0);
      envi::Job job;
      job.init = init.data();
      job.windows = 1;
      job.runs = 3;
      job.steps = 4;
      job.threads = 1;
      Discard sink(m.channels());
      envi::simulate(m, envi::Controller::parse(R"({"name": "pid", "params": {"ki": 1}})"), job, sink);
      ++loaded;
    } catch (const envi::ModelError&) {
      ++rejected;
    } catch (const std::exception& e) {
      std::fprintf(stderr, "%s: unexpected %s\n", argv[i], e.what());
      return 3;
    }
  }
  std::printf("fuzz: %d files, loaded %ld, rejected %ld\n", argc - 1, loaded, rejected);
  return 0;
}
