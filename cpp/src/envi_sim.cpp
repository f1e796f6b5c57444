// envi_sim: closed-loop simulation from the command line, without Python.
//
//   envi_sim --model m.onnx --init log_30_0.csv [more.csv ...] [--controller lane-keeping --param x=30]
//            [--runs 100] [--steps 500] [--out DIR] [--metrics FILE|-] ...   (see kUsage)
//
// Runs are simulated in chunks; each chunk's logs and metric rows are written before the next
// starts, so memory stays flat however many runs are asked for (with --metrics-only nothing but
// the running metric sums outlives a block).
#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <limits>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <dirent.h>
#include <fstream>
#include <iostream>
#include <map>
#include <memory>
#include <mutex>
#include <pthread.h>
#include <csignal>
#include <thread>
#include <sstream>
#include <sys/stat.h>
#include <sys/statvfs.h>
#include <unistd.h>

#include "envi/controller.hpp"
#include "envi/csvlog.hpp"
#include "envi/engine.hpp"
#include "envi/ensemble.hpp"
#include "envi/json.hpp"
#include "envi/metrics.hpp"
#include "envi/model.hpp"

using namespace envi;

namespace {

const char* kUsage =
    "usage: envi_sim --model MODEL.onnx --init LOG.csv [LOG.csv ...] [options]\n"
    "  --model FILE ...     exported envi model (required); several files are the members of a seed ensemble\n"
    "                       (envi-export --member k), each run drawn by one of them as envi simulate does\n"
    "  --init LOG.csv ...   real logs whose first `history` rows start the runs (required)\n"
    "  --controller C       a registered name (lane-keeping, bang-bang, pid, combine), a JSON spec\n"
    "                       {\"name\": ..., \"params\": {...}} or @FILE holding one (default: the model's\n"
    "                       training controller from its envi.controllers metadata, when it has exactly one)\n"
    "  --param K=V ...      parameters of a controller given by name (numbers where possible)\n"
    "  --steps T            steps after the initial window (default: each log's length minus the history)\n"
    "  --runs N             runs per initial window (default 1)\n"
    "  --seed S             seed of a stochastic model's draws (default 0)\n"
    "  --threads K          worker threads (default 0: one per core; at most 1024)\n"
    "  --block B            runs per block of the batched engine (default 256; 1 to 65536)\n"
    "  --out DIR            write every run as a log (CSV + .meta.json sidecar) into DIR; refused when DIR\n"
    "                       already holds logs\n"
    "  --force              replace the logs --out already holds (its CSV files and .meta.json sidecars are\n"
    "                       deleted once the new run has been written; any other file stays)\n"
    "  --metrics FILE|-     write the driving metrics as JSON (- for standard output)\n"
    "  --metrics-only       keep no traces, only the metrics (needs --metrics)\n"
    "  --centre X           lane centre of the metrics (default 40)\n"
    "  --band X             half-width of the steady band (default 10)\n"
    "  --skip N             rows left out of the metrics (default: the model's history)\n"
    "Options take their value as --opt VALUE or --opt=VALUE. Errors: one line, exit code 2.\n"
    "Counts are refused before any work when their buffers, metrics or logs cannot fit this machine\n"
    "(cpp/README.md, Limits of envi_sim).\n";

struct Args {
  std::string model, controller, out, metrics;  // model: the first of `models`, which names them in messages
  std::vector<std::string> models;
  std::string controller_file;  // --controller @FILE: the file the spec in `controller` was read from
  std::vector<std::string> init, params;
  long steps = -1, runs = 1, skip = -1;  // -1: each log's length minus the history; the history
  uint64_t seed = 0;
  int threads = 0, block = 256;
  double centre = 40.0, band = 10.0;
  bool metrics_only = false;
  bool force = false;  // --force: replace the logs --out already holds
};

// Limits of the numeric options, each for a reason (cpp/README.md, "Limits of envi_sim"):
// a worker thread beyond this many only time-slices the same cores and reserves its own stack;
constexpr long kMaxThreads = 1024;
// a block is one GEMM's columns and is held per thread: beyond this it stops paying and only grows
// the per-thread buffers (the engine already caps it at the number of runs);
constexpr long kMaxBlock = 65536;
// the random draws are keyed by a 32-bit step counter (rng.hpp): past it a run would repeat draws.
constexpr long kMaxLength = 0xFFFFFFFFL;

// An integer option in [lo, hi]; anything else (a fraction, an overflow, a sign) names the option.
long to_long(const std::string& flag, const std::string& v, long lo, long hi) {
  char* end = nullptr;
  errno = 0;
  long x = std::strtol(v.c_str(), &end, 10);
  if (v.empty() || *end || std::isspace(static_cast<unsigned char>(v[0])))
    throw std::invalid_argument(flag + ": not an integer: " + v);
  if (errno != ERANGE && x < 0 && lo == 0) throw std::invalid_argument(flag + " must not be negative, not " + v);
  if (errno == ERANGE || x < lo || x > hi)
    throw std::invalid_argument(flag + " must be between " + std::to_string(lo) + " and " + std::to_string(hi) + ", not " + v);
  return x;
}

// A finite number: nan or inf on the command line would be written into the metrics as such.
double to_double(const std::string& flag, const std::string& v) {
  char* end = nullptr;
  double x = std::strtod(v.c_str(), &end);
  if (v.empty() || *end || std::isspace(static_cast<unsigned char>(v[0])))
    throw std::invalid_argument(flag + ": not a number: " + v);
  if (!std::isfinite(x)) throw std::invalid_argument(flag + " must be a finite number, not " + v);
  return x;
}

// Refuses a FIFO, device or folder before it is opened: reading one would hang or mean nothing.
void require_regular_file(const std::string& flag, const std::string& path) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0)
    throw std::invalid_argument(flag + " " + path + ": cannot read (" + std::strerror(errno) + ")");
  if (!S_ISREG(st.st_mode)) throw std::invalid_argument(flag + " " + path + ": not a regular file");
}

// Refuses an output file that is one of the command's inputs (the same file by any path): '--metrics
// m.onnx' or '--metrics log_30_1.csv' once replaced the model or the initial log, exit 0 (as
// envi_py.files.refuse_overwriting does for the Python commands).
void refuse_overwriting(const std::string& flag, const std::string& out, const std::vector<std::string>& inputs) {
  struct stat o {};
  if (out == "-" || ::stat(out.c_str(), &o) != 0) return;
  for (const auto& in : inputs) {
    struct stat i {};
    if (::stat(in.c_str(), &i) == 0 && i.st_dev == o.st_dev && i.st_ino == o.st_ino)
      throw std::invalid_argument(flag + " " + out + ": is an input of this command (" + in + "); nothing overwritten");
  }
}

Args parse(int argc, char** argv) {
  Args a;
  for (int i = 1; i < argc; ++i) {
    std::string f = argv[i], inline_value;
    bool has_inline = false;
    if (f.rfind("--", 0) == 0 && f.find('=') != std::string::npos) {
      inline_value = f.substr(f.find('=') + 1);
      f = f.substr(0, f.find('='));
      has_inline = true;
    }
    auto val = [&]() -> std::string {
      if (has_inline) return inline_value;
      if (i + 1 >= argc || std::strncmp(argv[i + 1], "--", 2) == 0) throw std::invalid_argument(f + " needs a value");
      return argv[++i];
    };
    // the values of a list option run up to the next option
    auto more = [&](std::vector<std::string>& list) {
      list.push_back(val());
      while (i + 1 < argc && std::strncmp(argv[i + 1], "--", 2) != 0) list.push_back(argv[++i]);
    };
    if (f == "--model") more(a.models);
    else if (f == "--init") more(a.init);
    else if (f == "--controller") a.controller = val();
    else if (f == "--param") more(a.params);
    else if (f == "--steps") a.steps = to_long(f, val(), 1, kMaxLength);
    else if (f == "--runs") a.runs = to_long(f, val(), 1, std::numeric_limits<long>::max());
    else if (f == "--seed") a.seed = uint64_t(to_long(f, val(), 0, std::numeric_limits<long>::max()));
    else if (f == "--threads") a.threads = int(to_long(f, val(), 0, kMaxThreads));
    else if (f == "--block") a.block = int(to_long(f, val(), 1, kMaxBlock));
    else if (f == "--out") a.out = val();
    else if (f == "--metrics") a.metrics = val();
    else if (f == "--metrics-only" && !has_inline) a.metrics_only = true;
    else if (f == "--force" && !has_inline) a.force = true;
    else if (f == "--centre") a.centre = to_double(f, val());
    else if (f == "--band") {
      const std::string v = val();
      a.band = to_double(f, v);
      if (a.band < 0) throw std::invalid_argument("--band must not be negative, not " + v);
    }
    else if (f == "--skip") a.skip = to_long(f, val(), 0, kMaxLength);
    else if (f == "-h" || f == "--help") { std::cout << kUsage; std::exit(0); }
    else throw std::invalid_argument("unknown option " + std::string(argv[i]) + " (see --help)");
  }
  if (a.models.empty() || a.init.empty()) throw std::invalid_argument("--model and --init are required (see --help)");
  a.model = a.models[0];
  if (a.metrics_only && a.metrics.empty()) throw std::invalid_argument("--metrics-only needs --metrics FILE (or -)");
  if (!a.metrics_only && a.out.empty() && a.metrics.empty()) throw std::invalid_argument("nothing to write: give --out and/or --metrics");
  if (!a.params.empty() && (a.controller.empty() || a.controller[0] == '{' || a.controller[0] == '@'))
    throw std::invalid_argument("--param goes with a controller given by name (--controller NAME)");
  if (a.force && a.out.empty()) throw std::invalid_argument("--force replaces the logs of --out: give --out DIR");
  if (!a.controller.empty() && a.controller[0] == '@') {
    a.controller_file = a.controller.substr(1);
    require_regular_file("--controller", a.controller_file);
    std::ifstream in(a.controller_file);
    if (!in) throw std::invalid_argument("--controller " + a.controller_file + ": cannot read (" + std::strerror(errno) + ")");
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

// A --param value as envi_py.controllers.parse_params reads it: float(value) where that parses
// (surrounding spaces and a sign allowed), else the text. A non-finite number is refused, as the
// Python CLI refuses it (finite_numbers): a NaN gain simulates NaN logs.
Json param_value(const std::string& item, const std::string& value) {
  std::string t = value;
  t.erase(0, t.find_first_not_of(" \t\r\n\f\v") == std::string::npos ? t.size() : t.find_first_not_of(" \t\r\n\f\v"));
  t.erase(t.find_last_not_of(" \t\r\n\f\v") + 1);
  const bool hex = t.find_first_of("xX") != std::string::npos;  // strtod reads hex, float() does not
  char* end = nullptr;
  double v = std::strtod(t.c_str(), &end);
  if (t.empty() || hex || end != t.c_str() + t.size()) return str(value);
  if (!std::isfinite(v)) throw std::invalid_argument("--param " + item + ": not a finite number");
  return num(v);
}

// How errors name the controller option: with the file it was read from, if any.
std::string controller_option(const Args& a) {
  return a.controller_file.empty() ? std::string("--controller") : "--controller " + a.controller_file;
}

// The controller to run: a JSON spec as given, a registered name with its --param values, or the
// model's only training controller (its envi.controllers metadata). Its numbers must be finite.
Json controller_spec(const Args& a, const Model& m) {
  if (a.controller.empty() && a.controller_file.empty()) {
    Json list = Json::parse(m.metadata_value("envi.controllers"));
    size_t n = list.type == Json::Type::Array ? list.array.size() : 0;
    if (n != 1)
      throw std::invalid_argument(a.model + ": the model records " + std::to_string(n) +
                                  " training controller(s); choose one with --controller");
    if (!all_finite(list.array[0])) throw std::invalid_argument(a.model + ": the model's training controller holds a non-finite number");
    return list.array[0];
  }
  size_t first = a.controller.find_first_not_of(" \t\r\n");
  // a spec from @FILE is JSON whatever it starts with (an empty file is not "no controller")
  if (!a.controller_file.empty() || (first != std::string::npos && a.controller[first] == '{')) {
    const std::string where = controller_option(a);
    Json spec;
    try {
      spec = Json::parse(a.controller);
    } catch (const std::exception& e) {
      throw std::invalid_argument(where + ": " + e.what());
    }
    if (!all_finite(spec)) throw std::invalid_argument(where + ": the spec holds a non-finite number (NaN or Infinity)");
    return spec;
  }
  std::vector<std::pair<std::string, Json>> params;  // as envi_py.controllers.parse_params: the last of a name wins
  for (const std::string& item : a.params) {
    size_t eq = item.find('=');
    if (eq == std::string::npos || eq == 0) throw std::invalid_argument("--param " + item + ": expected name=value");
    std::string key = item.substr(0, eq);
    key.erase(0, key.find_first_not_of(" \t"));
    key.erase(key.find_last_not_of(" \t") + 1);
    if (key.empty()) throw std::invalid_argument("--param " + item + ": expected name=value");
    Json v = param_value(item, item.substr(eq + 1));
    auto same = std::find_if(params.begin(), params.end(), [&](const auto& kv) { return kv.first == key; });
    if (same != params.end()) same->second = v;
    else params.emplace_back(key, v);
  }
  return obj({{"name", str(a.controller)}, {"params", obj(std::move(params))}});
}

// Initial windows that run for the same number of steps, in the order they were first seen.
struct Group {
  long steps;
  std::vector<long> windows;
};

// The streamed metrics are the lane-keeping preset's eight (metrics.hpp): a model of another system
// (its description in the metadata names no such preset) declares other goals, which envi verify
// and envi check score from traces; scoring it with lane metrics would report figures about nothing.
void check_metrics_apply(const Model& m, const std::string& path) {
  Json system = Json::parse(m.metadata_value("envi.system"));
  if (system.is_null()) return;  // exported before descriptions were recorded: the lane-keeping robot
  const Json* preset = system.find("preset");
  if (preset && !preset->is_null() && preset->as_string() == "lane-keeping") return;
  const Json* name = system.find("name");
  throw std::invalid_argument(path + ": --metrics streams the lane-keeping preset's eight driving metrics, and this model's system '" +
                              (name && !name->is_null() ? name->as_string() : std::string("?")) +
                              "' declares other goals: write traces with --out and score them with envi verify or envi check");
}

// Runs per chunk of a length group: a whole number of blocks (so block boundaries, hence results,
// do not depend on it), enough to keep every thread busy; logs bound it by memory (~64 MB of traces).
long chunk_runs(long length, long channels, const Plan& full, bool want_logs) {
  long blocks_per_chunk = 16;
  if (want_logs) blocks_per_chunk = std::max<long>(1, std::min<long>(16, (long(8) << 20) / std::max<long>(1, length * channels * full.block)));
  return blocks_per_chunk * full.block;
}

double gib(double bytes) { return bytes / double(1L << 30); }

// A size in the unit that shows it (a few KiB once read "0.0 GiB").
std::string gib_text(double bytes) {
  char buf[32];
  if (bytes >= double(1L << 30))
    std::snprintf(buf, sizeof buf, "%.1f GiB", gib(bytes));
  else if (bytes >= double(1L << 20))
    std::snprintf(buf, sizeof buf, "%.1f MiB", bytes / double(1L << 20));
  else
    std::snprintf(buf, sizeof buf, "%.0f KiB", bytes / 1024.0);
  return buf;
}

// Free bytes of the file system holding `path` (a folder) or, for "-", standard output when it is
// a file; -1 when that cannot be known (a pipe or terminal).
double free_bytes(const std::string& path) {
  struct statvfs vfs {};
  if (path == "-") {
    struct stat st {};
    if (::fstat(STDOUT_FILENO, &st) != 0 || !S_ISREG(st.st_mode) || ::fstatvfs(STDOUT_FILENO, &vfs) != 0) return -1;
  } else if (::statvfs(path.c_str(), &vfs) != 0) {
    return -1;
  }
  return double(vfs.f_bavail) * double(vfs.f_frsize);
}

// The folder holding `path` ("sim/" and "sim" alike: the folder holding sim).
std::string parent_of(std::string path) {
  while (path.size() > 1 && path.back() == '/') path.pop_back();
  size_t slash = path.find_last_of('/');
  return slash == std::string::npos ? "." : slash == 0 ? "/" : path.substr(0, slash);
}

// Refuses, before any work, a run count (with the steps) that this machine cannot hold or whose
// results cannot be written (cpp/README.md, "Limits of envi_sim"): the index arithmetic must fit
// 64 bits, the buffers envi_sim keeps at once must fit in physical memory, so must the metrics
// document's rows in the reader that loads it, and what envi_sim must at least write (a log per
// run, a metrics row per run) must fit in the destination's free space.
void check_capacity(const Args& a, const Model& m, const std::vector<Group>& groups, bool want_logs, bool want_metrics,
                    bool streamed, int members) {
  const long l = m.history, c = m.channels();
  long windows = 0, total = 0;
  for (const Group& g : groups) windows += long(g.windows.size());
  const std::string runs = "--runs " + std::to_string(a.runs);
  if (__builtin_mul_overflow(windows, a.runs, &total))
    throw std::invalid_argument(runs + ": " + std::to_string(windows) + " initial logs x that many runs do not fit a 64-bit count");
  double held = 0, logs_bytes = 0;
  for (const Group& g : groups) {
    const long length = l + g.steps, group_runs = long(g.windows.size()) * a.runs;
    long cells = 0;
    if (__builtin_mul_overflow(group_runs, length * c, &cells))
      throw std::invalid_argument(runs + " x " + std::to_string(length) + " rows x " + std::to_string(c) + " channels do not fit a 64-bit index");
    Job job;
    job.windows = long(g.windows.size());
    job.runs = a.runs;
    job.threads = a.threads;
    job.block = a.block;
    const Plan full = plan(job);
    const double chunk = double(std::min(chunk_runs(length, c, full, want_logs), group_runs));
    // the engine's per-thread block buffers (engine.cpp: hidden activations, window ring, rows)
    const double engine = double(full.threads) * full.block * (16.0 * m.max_width() + 8.0 * m.in_features() + 24.0 * c);
    double group = engine + chunk * 8 * 8;  // a chunk's metric rows
    if (want_logs) group += chunk * double(length) * double(c) * 8 + double(length) * 8;  // traces, times
    // an ensemble: each run's member, and a member's runs with a copy of each one's initial window
    if (members > 1) group += double(group_runs) * (4.0 + (8.0 + 8.0 * double(l) * double(c)) / members);
    held = std::max(held, group);
    // a run's CSV (>= 1 digit and 1 separator a cell) and its sidecar, each taking whole blocks of the
    // file system (4 KiB on most): counting characters alone let 10^8 short runs start on a disk they
    // would fill at 8 KiB a run
    const double csv = double(length) * double(c + 1) * 2 + 200;
    logs_bytes += double(group_runs) * (std::ceil(csv / 4096.0) * 4096.0 + 4096.0);
  }
  if (want_metrics && !streamed) held += double(total) * 8 * 8;  // kept in window order until the end
  const double memory = double(::sysconf(_SC_PHYS_PAGES)) * double(::sysconf(_SC_PAGE_SIZE));
  if (memory > 0 && held > memory)
    throw std::invalid_argument(runs + (a.steps >= 0 ? " --steps " + std::to_string(a.steps) : std::string()) + " needs " +
                                gib_text(held) + " of buffers, more than this machine's " + gib_text(memory) +
                                " of memory (fewer runs or steps, or fewer lengths of initial log at once)");
  // The metrics are one JSON document with a row per run: whoever reads it (json.load, envi_py)
  // holds at least its eight doubles a run, on standard output as much as in a file.
  if (want_metrics && memory > 0 && double(total) * 64 > memory)
    throw std::invalid_argument(runs + ": a metrics document of " + std::to_string(total) + " rows needs at least " +
                                gib_text(double(total) * 64) + " in the reader that loads it, more than this machine's " +
                                gib_text(memory) + " of memory (fewer runs, or several documents)");
  auto fits = [&](const std::string& where, const std::string& what, double bytes) {
    const double space = free_bytes(where);
    if (space >= 0 && bytes > space)
      throw std::invalid_argument(runs + ": " + what + " would take at least " + gib_text(bytes) + ", and " +
                                  (where == "-" ? std::string("standard output's file system") : where) + " has " +
                                  gib_text(space) + " free");
  };
  struct stat st {};
  if (want_logs) fits(::stat(a.out.c_str(), &st) == 0 ? a.out : parent_of(a.out), "the logs in --out " + a.out, logs_bytes);
  if (want_metrics)  // a row of eight numbers a run, each at least "0.0" and its separator
    fits(a.metrics == "-" ? "-" : parent_of(a.metrics), "the metrics in --metrics " + a.metrics, double(total) * 42);
}

bool ends_with(const std::string& s, const std::string& suffix) {
  return s.size() > suffix.size() && s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}

// The logs `folder` holds, as envi_py.logs.folder_logs counts them: every file named *.csv or
// *.meta.json whose name does not start with '.' (a folder so named is no log). Sorted names.
std::vector<std::string> folder_logs(const std::string& folder) {
  std::vector<std::string> names;
  DIR* dir = ::opendir(folder.c_str());
  if (!dir) return names;
  while (const dirent* e = ::readdir(dir)) {
    const std::string name = e->d_name;
    if (name.empty() || name[0] == '.' || !(ends_with(name, ".csv") || ends_with(name, ".meta.json"))) continue;
    struct stat st {};
    if (::stat((folder + "/" + name).c_str(), &st) == 0 && S_ISDIR(st.st_mode)) continue;
    names.push_back(name);
  }
  ::closedir(dir);
  std::sort(names.begin(), names.end());
  return names;
}

long count_csv(const std::vector<std::string>& names) {
  return long(std::count_if(names.begin(), names.end(), [](const std::string& n) { return ends_with(n, ".csv"); }));
}

// "3 logs", or "2 log sidecars" when it holds sidecars only, as envi_py.logs.refuse_earlier_logs says it.
std::string logs_text(const std::vector<std::string>& held) {
  const long csv = count_csv(held), n = csv ? csv : long(held.size());
  return std::to_string(n) + (csv ? " log" : " log sidecar") + (n != 1 ? "s" : "");
}

// As envi simulate refuses it (envi_py.logs.refuse_earlier_logs): new runs written among an earlier
// run's logs would be read back as one set.
void refuse_earlier_logs(const std::string& out, bool force) {
  const auto held = folder_logs(out);
  if (!held.empty() && !force)
    throw std::invalid_argument("--out " + out + ": holds " + logs_text(held) +
                                " of an earlier run; pass --force to replace them (other files stay) or choose an empty folder");
}

std::string real_path(const std::string& path) {
  char* r = ::realpath(path.c_str(), nullptr);
  if (!r) return std::string();
  std::string s = r;
  std::free(r);
  return s;
}

// What a run has written but not yet moved into place (the staged logs, the metrics document) is
// discarded when the run fails or is interrupted. One lock covers every write into a pending place,
// every move into place, every discard and the list itself: a signal's cleanup never races a file
// being written, moved in or destroyed.
class Pending {
 public:
  Pending(const Pending&) = delete;
  Pending& operator=(const Pending&) = delete;
  static std::mutex& lock() {
    static std::mutex m;
    return m;
  }
  // discards everything still pending (the caller holds lock()); true when something was
  static bool discard_all() {
    bool any = false;
    for (Pending* p : live()) any = p->discard() || any;
    return any;
  }

 protected:
  Pending() = default;
  ~Pending() = default;
  // a derived class enlists once set up and delists in its destructor, both under lock()
  void enlist() { live().push_back(this); }
  void delist() {
    auto& l = live();
    l.erase(std::remove(l.begin(), l.end(), this), l.end());
  }
  virtual bool discard() = 0;  // true when something was pending

 private:
  static std::vector<Pending*>& live() {
    static std::vector<Pending*> l;
    return l;
  }
};

// SIGINT, SIGTERM and SIGHUP are blocked in every thread and taken by one watcher thread, which
// discards what is pending in ordinary context (a handler may not walk a folder) and exits with
// 128 + the signal, as a shell reports a killed command: a killed envi_sim leaves --out and
// --metrics as they were, as envi simulate does.
void watch_for_interruption() {
  static sigset_t signals;
  sigemptyset(&signals);
  for (int sig : {SIGINT, SIGTERM, SIGHUP}) sigaddset(&signals, sig);
  if (::pthread_sigmask(SIG_BLOCK, &signals, nullptr) != 0) return;  // then the signals keep their default action
  std::thread([] {
    int sig = 0;
    if (::sigwait(&signals, &sig) != 0) return;
    std::lock_guard<std::mutex> hold(Pending::lock());
    const bool discarded = Pending::discard_all();
    const std::string what = std::string("envi_sim: interrupted (") +
                             (sig == SIGINT ? "SIGINT" : sig == SIGTERM ? "SIGTERM" : "SIGHUP") + ")" +
                             (discarded ? "; --out and --metrics are left as they were" : "") + "\n";
    if (::write(STDERR_FILENO, what.data(), what.size()) < 0) {
      // nothing more to do: the exit status still says it
    }
    std::_Exit(128 + sig);
  }).detach();
}

// The metrics document is written to a hidden file beside --metrics and renamed onto it when
// complete: a run that fails or is interrupted half-way leaves an earlier document whole, and
// never a truncated one.
class PendingFile : public Pending {
 public:
  explicit PendingFile(const std::string& target) : target_(target) {
    const auto slash = target.rfind('/');
    std::string pattern = slash == std::string::npos ? "." + target + ".partial-XXXXXX"
                                                     : target.substr(0, slash + 1) + "." + target.substr(slash + 1) + ".partial-XXXXXX";
    std::lock_guard<std::mutex> hold(lock());
    const int fd = ::mkstemp(pattern.data());
    if (fd < 0) throw std::runtime_error("--metrics " + target + ": cannot write (" + std::strerror(errno) + ")");
    const mode_t mask = ::umask(0);  // mkstemp's 0600, widened as a plainly opened file would be
    ::umask(mask);
    const int chmod_rc = ::fchmod(fd, 0666 & ~mask);
    ::close(fd);
    path_ = pattern;
    enlist();
    (void)chmod_rc;  // a file system without modes keeps mkstemp's: the document is still whole
  }
  ~PendingFile() {
    std::lock_guard<std::mutex> hold(lock());
    discard();
    delist();
  }
  const std::string& path() const { return path_; }
  // renames the complete document onto --metrics
  void commit() {
    std::lock_guard<std::mutex> hold(lock());
    if (::rename(path_.c_str(), target_.c_str()) != 0)
      throw std::runtime_error("--metrics " + target_ + ": cannot move the document into place (" + std::strerror(errno) + ")");
    path_.clear();
  }

 protected:
  bool discard() override {
    if (path_.empty()) return false;
    ::unlink(path_.c_str());
    path_.clear();
    return true;
  }

 private:
  std::string target_, path_;
};

// The new logs are written into a hidden folder inside --out and moved in only when the whole run
// has been written (envi_py.logs.staged_logs): a run that fails half-way leaves --out as it was,
// neither an earlier run lost nor half of a new one mixed into it.
class Staging : public Pending {
 public:
  // made_out: this run created --out, so a run that fails or is interrupted removes it again (when
  // empty), as envi simulate does
  Staging(const std::string& out, bool made_out) : out_(out), made_out_(made_out) {
    std::string pattern = out + "/.staging-XXXXXX";
    std::lock_guard<std::mutex> hold(lock());
    if (!::mkdtemp(pattern.data()))
      throw std::runtime_error("--out " + out + ": cannot create a staging folder (" + std::strerror(errno) + ")");
    dir_ = pattern;
    enlist();
  }
  ~Staging() {
    std::lock_guard<std::mutex> hold(lock());
    discard();
    delist();
  }
  const std::string& dir() const { return dir_; }

  // Deletes the earlier logs (with --force; without it, refuses logs that appeared during the run)
  // and moves the new ones in. Returns how many earlier CSV logs were replaced.
  long commit(bool force) {
    std::lock_guard<std::mutex> hold(lock());
    const auto held = folder_logs(out_);
    if (!held.empty() && !force)
      throw std::runtime_error("--out " + out_ + ": " + logs_text(held) + " appeared there during the run; nothing was written " +
                               "(pass --force to replace them)");
    for (const auto& name : held)
      if (::unlink((out_ + "/" + name).c_str()) != 0 && errno != ENOENT)
        throw std::runtime_error("--out " + out_ + ": cannot delete the earlier log " + name + " (" + std::strerror(errno) + ")");
    for (const auto& name : entries())
      if (::rename((dir_ + "/" + name).c_str(), (out_ + "/" + name).c_str()) != 0)
        throw std::runtime_error("--out " + out_ + ": cannot move " + name + " into place (" + std::strerror(errno) + ")");
    made_out_ = false;  // it holds the run now
    discard();
    return count_csv(held);
  }

 protected:
  bool discard() override {
    if (dir_.empty()) return false;
    for (const auto& name : entries()) ::unlink((dir_ + "/" + name).c_str());
    ::rmdir(dir_.c_str());
    dir_.clear();
    if (made_out_) ::rmdir(out_.c_str());  // only when empty: nothing else is ever removed
    return true;
  }

 private:
  std::vector<std::string> entries() const {
    std::vector<std::string> names;
    if (DIR* dir = ::opendir(dir_.c_str())) {
      while (const dirent* e = ::readdir(dir))
        if (std::strcmp(e->d_name, ".") != 0 && std::strcmp(e->d_name, "..") != 0) names.push_back(e->d_name);
      ::closedir(dir);
    }
    std::sort(names.begin(), names.end());
    return names;
  }
  std::string out_, dir_;
  bool made_out_;
};

// The output folder, checked before any work and created only after every check has passed: an
// existing one must not hold logs (unless --force replaces them) nor the initial logs themselves.
void check_out_folder(const std::string& out, bool force, const std::vector<std::string>& init) {
  struct stat st {};
  if (::stat(out.c_str(), &st) == 0) {
    if (!S_ISDIR(st.st_mode)) throw std::invalid_argument("--out " + out + ": exists and is not a folder");
    if (::access(out.c_str(), W_OK) != 0) throw std::invalid_argument("--out " + out + ": cannot write (" + std::strerror(errno) + ")");
    refuse_earlier_logs(out, force);
    const std::string folder = real_path(out);
    for (const auto& p : init)  // --force would delete the very logs the simulation starts from
      if (!folder.empty() && real_path(parent_of(p)) == folder)
        throw std::invalid_argument("--out " + out + ": holds the initial log " + p + "; simulate into another folder");
    return;
  }
  const std::string parent = parent_of(out);
  if (::stat(parent.c_str(), &st) != 0 || !S_ISDIR(st.st_mode))
    throw std::invalid_argument("--out " + out + ": its parent folder " + parent + " does not exist");
  if (::access(parent.c_str(), W_OK) != 0) throw std::invalid_argument("--out " + out + ": cannot create (" + std::strerror(errno) + ")");
}

// An exported member says which of how many it is (envi.hyper's "member", envi-export --member): a
// member given twice is an error, and members given without the rest are run as the ensemble of
// those given, said on stderr rather than silently (envi simulate draws runs by every member).
void note_partial_ensemble(const std::vector<Model>& models, const std::vector<std::string>& paths) {
  std::map<long, size_t> given;  // member index -> its --model position
  long of = 0;
  for (size_t k = 0; k < models.size(); ++k) {
    const Json hyper = Json::parse(models[k].metadata_value("envi.hyper"));
    const Json* member = hyper.find("member");
    if (member == nullptr) continue;
    const long index = long(member->at("index").as_number()), size = long(member->at("of").as_number());
    if (of != 0 && size != of)
      throw std::invalid_argument("--model " + paths[k] + ": a member of a seed ensemble of " + std::to_string(size) +
                                  ", the other members given are of one of " + std::to_string(of));
    of = size;
    if (const auto twice = given.find(index); twice != given.end())
      throw std::invalid_argument("--model " + paths[k] + ": member " + std::to_string(index) + " of the seed ensemble, as " +
                                  paths[twice->second] + " is; give each member once");
    given.emplace(index, k);
  }
  if (of == 0 || long(given.size()) == of) return;
  std::string which;
  for (const auto& [index, k] : given) which += (which.empty() ? "" : ", ") + std::to_string(index);
  std::cerr << "envi_sim: note: --model gives member" << (given.size() > 1 ? "s " : " ") << which << " of a seed ensemble of "
            << of << "; the runs are drawn by " << (given.size() > 1 ? "these " + std::to_string(given.size()) : "it")
            << " only (envi simulate draws them by all " << of << ")\n";
}

// The models of --model: one, or the members of a seed ensemble, which must read and say the same
// (what envi_py.model.Checkpoint.ensemble requires of its members); only their weights and fitted
// step-noise shapes may differ.
std::vector<Model> load_members(const std::vector<std::string>& paths) {
  static const char* kShared[] = {"envi.schema", "envi.normaliser", "envi.history", "envi.period_ms", "envi.head",
                                  "envi.post",   "envi.limit_events", "envi.residual", "envi.layers", "envi.context",
                                  "envi.system"};
  std::vector<Model> out;
  for (const auto& p : paths) out.push_back(load_model_file(p));
  for (size_t k = 1; k < out.size(); ++k)
    for (const char* key : kShared)
      if (dump(Json::parse(out[k].metadata_value(key))) != dump(Json::parse(out[0].metadata_value(key))))
        throw std::invalid_argument("--model " + paths[k] + ": its " + key + " differs from " + paths[0] +
                                    "'s; the models given together must be members of one seed ensemble");
  note_partial_ensemble(out, paths);
  return out;
}

int run(const Args& a) {
  for (const auto& p : a.models) require_regular_file("--model", p);
  for (const auto& p : a.init) require_regular_file("--init", p);
  if (!a.metrics.empty()) {
    std::vector<std::string> inputs(a.models);
    inputs.insert(inputs.end(), a.init.begin(), a.init.end());
    if (!a.controller_file.empty()) inputs.push_back(a.controller_file);
    refuse_overwriting("--metrics", a.metrics, inputs);
  }
  const std::vector<Model> members = load_members(a.models);
  const Model& m = members[0];
  const int M = int(members.size());
  if (!a.metrics.empty()) check_metrics_apply(m, a.model);
  Json spec = controller_spec(a, m);
  Controller ctrl;
  try {
    ctrl = Controller::from_json(spec, m.period_ms);
    ctrl.check(m.n_state(), m.n_action());
  } catch (const std::exception& e) {  // a spec read from a file is named by its file
    if (a.controller_file.empty()) throw;
    throw std::invalid_argument(controller_option(a) + ": " + e.what());
  }
  const Json ctrl_json = Json::parse(ctrl.to_json());

  const long l = m.history, c = m.channels();
  std::vector<InitialWindow> windows;
  std::vector<Group> groups;
  for (const auto& p : a.init) {
    windows.push_back(read_initial_window(p, m));
    if (m.period_ms > 0 && windows.back().time.size() >= 3) {  // as envi_py.logs.require_signals
      const double median = median_period(windows.back().time);
      if (std::fabs(median - m.period_ms) > 0.1 * m.period_ms) {
        std::ostringstream msg;
        msg << "--init " << p << ": its rows are " << median << " ms apart (median), the model was trained at a "
            << m.period_ms << " ms period";
        throw std::invalid_argument(msg.str());
      }
    }
    long steps = a.steps >= 0 ? a.steps : windows.back().rows - l;
    if (steps == 0 && a.steps < 0)  // as envi_py.simulate.iter_simulate: a log of sigma_0 alone
      throw std::invalid_argument("--init " + p + ": " + std::to_string(l) +
                                  " rows, the model's window alone: no row is left to simulate; give --steps, or a longer log");
    auto g = std::find_if(groups.begin(), groups.end(), [&](const Group& x) { return x.steps == steps; });
    if (g == groups.end()) groups.push_back({steps, {}}), g = groups.end() - 1;
    g->windows.push_back(long(windows.size()) - 1);
  }
  MetricConfig mcfg{a.centre, a.band, a.skip >= 0 ? a.skip : l, 0};
  const bool want_logs = !a.metrics_only && !a.out.empty(), want_metrics = !a.metrics.empty();
  for (const Group& g : groups) {
    if (l + g.steps > kMaxLength)
      throw std::invalid_argument((a.steps >= 0 ? "--steps " + std::to_string(a.steps) : "an initial log's length") +
                                  ": runs longer than " + std::to_string(kMaxLength) + " rows would repeat their random draws");
    if (want_metrics && l + g.steps - mcfg.skip <= 0)
      throw std::invalid_argument("--skip " + std::to_string(mcfg.skip) + ": runs of " + std::to_string(l + g.steps) +
                                  " rows leave nothing to score");
  }
  if (want_logs) {  // every run's files are named by its initial log's run id: two alike would overwrite
    for (size_t i = 0; i < windows.size(); ++i)
      for (size_t j = 0; j < i; ++j)
        if (windows[i].run_id == windows[j].run_id)
          throw std::invalid_argument("--init " + a.init[i] + ": run id '" + windows[i].run_id + "' is also " + a.init[j] +
                                      "'s; their simulated logs in --out would overwrite each other");
    check_out_folder(a.out, a.force, a.init);
  }
  // metric rows are written as they come only when they come in window order: one length of
  // initial log and one model (an ensemble's members each take their share of the runs in turn)
  const bool streamed = groups.size() == 1 && M == 1;
  check_capacity(a, m, groups, want_logs, want_metrics, streamed, M);
  const long K = long(windows.size()), R = K * a.runs;

  std::ofstream metrics_file;
  std::unique_ptr<PendingFile> metrics_pending;
  std::ostream* mout = nullptr;
  // per-run metric rows in window order; written as they come when there is one group of windows
  std::vector<double> all_metrics;
  if (want_metrics) {
    if (a.metrics == "-") mout = &std::cout;
    else {
      struct stat st {};
      // a device, FIFO or link (/dev/null, /dev/stdout) is written as it is: renaming a file onto it
      // would replace the node itself
      const bool special = ::lstat(a.metrics.c_str(), &st) == 0 && !S_ISREG(st.st_mode);
      if (!special) metrics_pending = std::make_unique<PendingFile>(a.metrics);
      metrics_file.open(special ? a.metrics : metrics_pending->path());
      if (!metrics_file) throw std::runtime_error("--metrics " + a.metrics + ": cannot write");
      mout = &metrics_file;
    }
    std::string steps;
    if (streamed) steps = std::to_string(groups[0].steps);
    else
      for (const auto& w : windows) steps += (steps.empty() ? "[" : ", ") + std::to_string(a.steps >= 0 ? a.steps : w.rows - l);
    if (!streamed) steps += "]";
    *mout << "{\"metrics\": [";
    for (int k = 0; k < 8; ++k) *mout << (k ? ", " : "") << '"' << kMetricNames[k] << '"';
    *mout << "], \"config\": {\"centre\": " << json_number(mcfg.centre) << ", \"band\": " << json_number(mcfg.band)
          << ", \"skip\": " << mcfg.skip << ", \"channel\": " << mcfg.channel << "}, \"model\": " << json_quote(a.model)
          << (M > 1 ? ", \"members\": " + std::to_string(M) : std::string()) << ", \"controller\": " << ctrl.to_json()
          << ", \"windows\": " << K << ", \"runs_per_window\": " << a.runs
          << ", \"steps\": " << steps << ", \"seed\": " << a.seed << ",\n\"per_run\": [";
    if (!streamed) all_metrics.assign(size_t(R) * 8, 0.0);
  }
  bool made_out = false;
  if (want_logs) {
    made_out = ::mkdir(a.out.c_str(), 0777) == 0;
    if (!made_out && errno != EEXIST) throw std::runtime_error("--out " + a.out + ": cannot create (" + std::strerror(errno) + ")");
  }
  std::unique_ptr<Staging> staging;
  if (want_logs) staging = std::make_unique<Staging>(a.out, made_out);
  long replaced = 0;
  std::vector<double> sums(8, 0.0), traces;
  MetricRows mrows;
  const std::string schema = m.metadata_value("envi.schema");
  Json schema_json = Json::parse(schema);
  // a simulated log's provenance, as envi_py.simulate.iter_simulate writes it (without its 'engine')
  const Json layers = Json::parse(m.metadata_value("envi.layers"));
  auto provenance = [&](const std::string& init_log, long replicate) {
    Json p = obj({{"init_log", str(init_log)},
                  {"model_algorithm", str(m.algorithm)},
                  {"seed", num(double(a.seed), true)},
                  {"replicate", num(double(replicate), true)}});
    if (!m.layers.empty()) p.object.emplace_back("layers", layers);
    if (M > 1) p.object.emplace_back("members", num(double(M), true));
    return p;
  };
  int threads_used = 1;
  long written = 0;  // metric rows written so far (streamed)
  for (const Group& grp : groups) {
    const long length = l + grp.steps, KG = long(grp.windows.size()), RG = KG * a.runs;
    const uint64_t group_seed = a.seed + 7919 * uint64_t(grp.steps);  // as envi_py.simulate.iter_simulate seeds a length group
    // an ensemble's runs as envi_py.simulate.ensemble_rollout shares them out: member mi simulates
    // the group's runs g with pick[g] == mi, one run per window row, with its own seed
    const std::vector<int> pick = M > 1 ? members_of_runs(M, RG, group_seed) : std::vector<int>();
    for (int mi = 0; mi < M; ++mi) {
      std::vector<long> mine;  // the group's runs this member simulates (a single model: all, unlisted)
      if (M > 1) {
        for (long g = 0; g < RG; ++g)
          if (pick[size_t(g)] == mi) mine.push_back(g);
        if (mine.empty()) continue;
      }
      std::vector<double> init;
      Job job;
      if (M == 1) {
        for (long k : grp.windows) init.insert(init.end(), windows[size_t(k)].values.begin(), windows[size_t(k)].values.end());
        job.windows = KG;
        job.runs = a.runs;
        job.seed = group_seed;
      } else {
        for (long g : mine) {
          const auto& v = windows[size_t(grp.windows[size_t(g / a.runs)])].values;
          init.insert(init.end(), v.begin(), v.end());
        }
        job.windows = long(mine.size());
        job.runs = 1;
        job.seed = group_seed + 15485863 * uint64_t(mi + 1);  // as ensemble_rollout seeds a member
      }
      job.init = init.data();
      job.steps = grp.steps;
      job.threads = a.threads;
      job.block = a.block;
      const long RJ = job.windows * job.runs;
      const Plan full = plan(job);
      threads_used = std::max(threads_used, full.threads);
      const long chunk = chunk_runs(length, c, full, want_logs);
      for (long first = 0; first < RJ; first += chunk) {
        Job part = job;
        part.first_run = first;
        part.n_runs = std::min(chunk, RJ - first);
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
        simulate(members[size_t(mi)], ctrl, part, sink);
        for (long i = 0; i < part.n_runs; ++i) {
          long g = M == 1 ? first + i : mine[size_t(first + i)], k = grp.windows[size_t(g / a.runs)], r = g % a.runs;
          if (want_metrics) {
            const double* row = mrows.rows.data() + size_t(i) * 8;
            for (int j = 0; j < 8; ++j) sums[size_t(j)] += row[j];
            if (streamed) {
              *mout << (written++ ? ",\n[" : "\n[");
              for (int j = 0; j < 8; ++j) *mout << (j ? ", " : "") << json_number(row[j]);
              *mout << "]";
            } else {
              std::copy_n(row, 8, all_metrics.data() + size_t(k * a.runs + r) * 8);
            }
          }
          if (want_logs) {
            const InitialWindow& w = windows[size_t(k)];
            double period = l > 1 ? median_period(w.time) : (m.period_ms > 0 ? m.period_ms : 40.0);
            std::vector<double> time(w.time);
            for (long t = 1; t <= grp.steps; ++t) time.push_back(w.time.back() + period * double(t));
            std::string run_id = w.run_id + "-sim" + std::to_string(r);
            Json meta = obj({{"schema_version", num(1, true)},
                             {"states", schema_json.at("states")},
                             {"actions", schema_json.at("actions")},
                             {"controller", ctrl_json},
                             {"period_ms", num(period)},
                             {"run_id", str(run_id)},
                             {"source", str("sim")},
                             {"provenance", provenance(w.name, r)}});
            std::lock_guard<std::mutex> hold(Pending::lock());  // not discarded by an interruption half-written
            write_log(staging->dir(), run_id, m, meta, time, traces.data() + size_t(i) * size_t(length) * size_t(c), length);
          }
        }
      }
    }
  }
  if (staging) replaced = staging->commit(a.force);
  if (want_metrics) {
    if (!streamed)
      for (long g = 0; g < R; ++g) {
        *mout << (g ? ",\n[" : "\n[");
        for (int j = 0; j < 8; ++j) *mout << (j ? ", " : "") << json_number(all_metrics[size_t(g) * 8 + size_t(j)]);
        *mout << "]";
      }
    *mout << "],\n\"mean\": [";
    for (int j = 0; j < 8; ++j) *mout << (j ? ", " : "") << json_number(sums[size_t(j)] / double(R));
    *mout << "]}\n";
    mout->flush();
    if (!*mout) throw std::runtime_error(a.metrics + ": write failed");
    if (metrics_pending) {
      metrics_file.close();
      if (!metrics_file) throw std::runtime_error(a.metrics + ": write failed");
      metrics_pending->commit();
    }
  }
  if (mout != &std::cout) {
    std::cerr << "envi_sim: " << R << " runs";
    if (streamed) std::cerr << " x " << groups[0].steps << " steps";
    std::cerr << " (" << threads_used << " threads)";
    if (replaced) std::cerr << "; replaced " << replaced << " earlier log" << (replaced != 1 ? "s" : "") << " in " << a.out;
    std::cerr << "\n";
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    watch_for_interruption();  // before any worker thread starts, so that all inherit the blocked signals
    return run(parse(argc, argv));
  } catch (const std::exception& e) {  // bad arguments, files, models or controllers alike
    std::string what = e.what();
    for (char& ch : what)
      if (ch == '\n') ch = ' ';
    std::cerr << "envi_sim: " << what << "\n";
    return 2;
  }
}
