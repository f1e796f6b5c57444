// The project's log format (envi_py/logs.py) on the C++ side: read the initial window of a real
// log, write a simulated run as CSV plus its `.meta.json` sidecar exactly as write_log does.
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

// First `model.history` data rows of a CSV log whose header holds the model's columns (any order).
InitialWindow read_initial_window(const std::string& path, const Model& model);

// Python's _fmt: integers without a decimal point, other values as repr(float).
std::string format_value(double v);

// Median period of a window's times, as float(np.median(np.diff(time))).
double median_period(const std::vector<double>& time);

// Writes <dir>/<run_id>.csv and its sidecar; rows is length x channels.
void write_log(const std::string& dir, const std::string& run_id, const Model& model, const Json& meta,
               const std::vector<double>& time, const double* rows, long length);

}  // namespace envi
