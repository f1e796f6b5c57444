#include "envi/csvlog.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <stdexcept>

namespace envi {
namespace {

std::string trim(const std::string& s) {
  size_t a = s.find_first_not_of(" \t\r"), b = s.find_last_not_of(" \t\r");
  return a == std::string::npos ? "" : s.substr(a, b - a + 1);
}

std::vector<std::string> split(const std::string& line) {
  std::vector<std::string> out;
  std::stringstream ss(line);
  std::string cell;
  while (std::getline(ss, cell, ',')) out.push_back(trim(cell));
  if (!line.empty() && line.back() == ',') out.push_back("");
  return out;
}

std::string stem(const std::string& name) {
  size_t dot = name.rfind('.');
  return dot == std::string::npos ? name : name.substr(0, dot);
}

std::string base(const std::string& path) {
  size_t slash = path.find_last_of('/');
  return slash == std::string::npos ? path : path.substr(slash + 1);
}

std::string dir_of(const std::string& path) {
  size_t slash = path.find_last_of('/');
  return slash == std::string::npos ? "." : path.substr(0, slash);
}

void write_atomic(const std::string& path, const std::string& text) {
  std::string tmp = dir_of(path) + "/." + base(path) + ".tmp";
  {
    std::ofstream out(tmp, std::ios::binary);
    out << text;
    if (!out.flush()) throw std::runtime_error(path + ": cannot write");
  }
  if (std::rename(tmp.c_str(), path.c_str()) != 0) throw std::runtime_error(path + ": cannot rename into place");
}

}  // namespace

InitialWindow read_initial_window(const std::string& path, const Model& model) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error(path + ": cannot open");
  std::vector<std::string> want{"time"};
  for (const auto& c : model.states) want.push_back(c.name);
  for (const auto& c : model.actions) want.push_back(c.name);
  std::string line;
  if (!std::getline(in, line)) throw std::runtime_error(path + ": empty file");
  auto header = split(line);
  std::vector<size_t> order;
  for (const auto& w : want) {
    auto it = std::find(header.begin(), header.end(), w);
    if (it == header.end()) throw std::runtime_error(path + ": row 1: missing column " + w);
    order.push_back(size_t(it - header.begin()));
  }
  InitialWindow win;
  win.name = base(path);
  win.run_id = stem(win.name);
  std::ifstream side(dir_of(path) + "/" + stem(win.name) + ".meta.json");
  if (side) {
    std::stringstream ss;
    ss << side.rdbuf();
    Json meta = Json::parse(ss.str());
    if (const Json* id = meta.find("run_id"))
      if (id->type == Json::Type::String) win.run_id = id->string;
  }
  long row = 1;
  while ((long)win.time.size() < model.history && std::getline(in, line)) {
    ++row;
    if (trim(line).empty()) continue;
    auto cells = split(line);
    if (cells.size() != header.size()) throw std::runtime_error(path + ": row " + std::to_string(row) + ": wrong number of cells");
    for (size_t k = 0; k < order.size(); ++k) {
      const std::string& c = cells[order[k]];
      char* end = nullptr;
      double v = std::strtod(c.c_str(), &end);
      if (c.empty() || end != c.c_str() + c.size() || !std::isfinite(v))
        throw std::runtime_error(path + ": row " + std::to_string(row) + ": column '" + want[k] + "' is not a finite number");
      (k == 0 ? win.time : win.values).push_back(v);
    }
  }
  if ((long)win.time.size() < model.history)
    throw std::runtime_error(path + ": fewer rows than the model's history of " + std::to_string(model.history));
  win.rows = long(win.time.size());
  while (std::getline(in, line))
    if (!trim(line).empty()) ++win.rows;
  return win;
}

std::string format_value(double v) {
  if (std::floor(v) == v && std::fabs(v) < 1e15) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%lld", static_cast<long long>(v));
    return buf;
  }
  return py_float(v);
}

double median_period(const std::vector<double>& time) {
  std::vector<double> d;
  for (size_t i = 1; i < time.size(); ++i) d.push_back(time[i] - time[i - 1]);
  if (d.empty()) return 0.0;
  std::sort(d.begin(), d.end());
  size_t n = d.size();
  return n % 2 ? d[n / 2] : (d[n / 2 - 1] + d[n / 2]) / 2;
}

void write_log(const std::string& dir, const std::string& run_id, const Model& model, const Json& meta,
               const std::vector<double>& time, const double* rows, long length) {
  const int c = model.channels();
  std::string text = "time";
  for (const auto& ch : model.states) text += "," + ch.name;
  for (const auto& ch : model.actions) text += "," + ch.name;
  text += "\n";
  for (long t = 0; t < length; ++t) {
    text += format_value(time[size_t(t)]);
    for (int k = 0; k < c; ++k) text += "," + format_value(rows[t * c + k]);
    text += "\n";
  }
  std::string csv = dir + "/" + run_id + ".csv";
  write_atomic(dir + "/" + run_id + ".meta.json", dump_indent1(meta) + "\n");  // sidecar first, as write_log
  write_atomic(csv, text);
}

}  // namespace envi
