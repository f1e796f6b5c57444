// The project's log format (envi_py/logs.py) on the C++ side: read the initial window of a real
// log, write a simulated run as CSV plus its `.meta.json` sidecar exactly as write_log does.
//
// The reader refuses what envi_py.logs.read_log refuses, with the same kind of one-line message
// naming the file (and row and column): a file that is not a regular UTF-8 text file, a bad
// header (a missing column, or one that neither the sidecar nor the model's recorded system
// description declares: its logged columns are required, its ignored ones may be there), a short
// or non-numeric row anywhere in the file, a time that does not increase, a value
// outside its channel's declared range (a saturating sensor's is clipped), a run id that is not a
// plain file name, and a sidecar that is not what LogMeta.from_json accepts.
// tests/test_envi_sim_bad_input.py keeps the two readers from drifting apart.
#pragma once
#include <string>
#include <vector>

#include "envi/json.hpp"
#include "envi/model.hpp"

namespace envi {

struct InitialWindow {
  std::string name;    // file name, e.g. log_30_0.csv
  std::string run_id;  // from the sidecar, else the file stem
  std::vector<double> time;    // history rows, ms
  std::vector<double> values;  // history x channels, physical
  long rows = 0;               // data rows in the whole log (its length)
};

// One column a log declares: its name, valid range and whether the sensor saturates there.
struct LogChannel {
  std::string name;
  double low, high;
  bool saturates = false;
};

// What a `.meta.json` sidecar declares, checked field by field as LogMeta.from_json checks it.
struct Sidecar {
  std::string run_id;  // empty when the sidecar names none
  std::vector<LogChannel> states, actions, logged;
  long last_break = 0;  // the last row that follows rows lost in transit ("breaks"); 0: none
};

// A sidecar file's content; throws std::runtime_error naming the file.
Sidecar read_sidecar(const std::string& path);

// Whether a run id is a plain file name (envi_py.logs.RUN_ID): it names the simulated log files.
bool is_run_id(const std::string& id);

// First `model.history` data rows of a CSV log that holds the model's columns (any order); every
// row of the file is checked. Throws std::runtime_error naming the file.
InitialWindow read_initial_window(const std::string& path, const Model& model);

// Python's _fmt: integers without a decimal point, other values as repr(float).
std::string format_value(double v);

// Median period of a window's times, as float(np.median(np.diff(time))).
double median_period(const std::vector<double>& time);

// Writes <dir>/<run_id>.csv and its sidecar; rows is length x channels.
void write_log(const std::string& dir, const std::string& run_id, const Model& model, const Json& meta,
               const std::vector<double>& time, const double* rows, long length);

}  // namespace envi
