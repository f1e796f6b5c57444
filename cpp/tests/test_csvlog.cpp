// The log reader (csvlog.cpp) and the JSON writer's non-finite numbers, without a model file:
// a hand-made Model carries the schema. tests/test_envi_sim_bad_input.py checks the same cases
// against the Python reader through envi_sim.
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <string>

#include "check.hpp"
#include "envi/csvlog.hpp"
#include "envi/json.hpp"

using namespace envi;

namespace {

std::string dir;

std::string write(const std::string& name, const std::string& text) {
  std::string path = dir + "/" + name;
  std::ofstream(path, std::ios::binary) << text;
  return path;
}

// color (state, 0..100, saturating when asked) and angle (action, -90..90); history 3
Model lane_model(bool saturates) {
  Model m;
  m.states = {{"color", "%", 0, 100}};
  m.actions = {{"angle", "deg", -90, 90}};
  m.history = 3;
  m.metadata = {{"envi.schema", std::string("{\"states\": [{\"name\": \"color\", \"unit\": \"%\", \"range\": [0, 100]") +
                                    (saturates ? ", \"saturates\": true" : "") +
                                    "}], \"actions\": [{\"name\": \"angle\", \"unit\": \"deg\", \"range\": [-90, 90]}]}"}};
  return m;
}

const char* kGood = "time,color,angle\n0,40,30\n40,45,30\n80,30,-30\n120,50,30\n";

}  // namespace

int main() {
  char tmpl[] = "/tmp/envi_csvlog_XXXXXX";
  dir = ::mkdtemp(tmpl);
  const Model m = lane_model(false);

  // a good log: the first history rows, the whole length, the stem as run id
  InitialWindow w = read_initial_window(write("good.csv", kGood), m);
  CHECK(w.rows == 4 && w.time.size() == 3 && w.values.size() == 6 && w.values[2] == 45 && w.run_id == "good");
  // columns in another order, CRLF line ends and a BOM read alike
  w = read_initial_window(write("crlf.csv", "\xEF\xBB\xBFtime,angle,color\r\n0,30,40\r\n40,30,45\r\n80,-30,30\r\n"), m);
  CHECK(w.rows == 3 && w.values[0] == 40 && w.values[1] == 30);

  // every row is checked, not only the history: the file and row are named
  CHECK_THROWS(std::runtime_error, read_initial_window(write("dec.csv", "time,color,angle\n0,40,30\n40,45,30\n30,30,-30\n"), m),
               "dec.csv: row 4: time 30 does not increase (previous 40)");
  CHECK_THROWS(std::runtime_error, read_initial_window(write("rep.csv", "time,color,angle\n0,40,30\n40,45,30\n80,30,-30\n80,30,-30\n"), m),
               "rep.csv: row 5: time 80 does not increase");
  CHECK_THROWS(std::runtime_error, read_initial_window(write("cut.csv", std::string(kGood) + "160,50"), m),
               "cut.csv: row 6: 2 cells, header has 3");
  CHECK_THROWS(std::runtime_error, read_initial_window(write("range.csv", std::string(kGood) + "160,101,30\n"), m),
               "range.csv: row 6: column 'color' is 101, outside its valid range [0, 100]");
  CHECK_THROWS(std::runtime_error, read_initial_window(write("nan.csv", "time,color,angle\n0,nan,30\n40,45,30\n80,30,-30\n"), m),
               "nan.csv: row 2: column 'color' is 'nan' (NaN/inf are not valid readings)");
  CHECK_THROWS(std::runtime_error, read_initial_window(write("hex.csv", "time,color,angle\n0,0x10,30\n40,45,30\n80,30,-30\n"), m),
               "column 'color' has non-numeric value '0x10'");
  CHECK_THROWS(std::runtime_error, read_initial_window(write("short.csv", "time,color,angle\n0,40,30\n"), m),
               "short.csv: 1 data rows, shorter than the 3 the history window needs");
  CHECK_THROWS(std::runtime_error, read_initial_window(write("miss.csv", "time,color\n0,40\n"), m), "row 1: missing column(s) angle");
  CHECK_THROWS(std::runtime_error, read_initial_window(write("empty.csv", ""), m), "empty.csv: empty file");
  CHECK_THROWS(std::runtime_error, read_initial_window(dir, m), "not a regular file");
  CHECK_THROWS(std::runtime_error, read_initial_window(dir + "/none.csv", m), "none.csv: cannot read");

  // a saturating sensor reads its limit: clipped, not refused
  w = read_initial_window(write("sat.csv", "time,color,angle\n0,140,30\n40,45,30\n80,30,-30\n"), lane_model(true));
  CHECK(w.values[0] == 100);

  // the sidecar: named in its errors, its ranges and run id used
  write("side.csv", kGood);
  write("side.meta.json", "{bad");
  CHECK_THROWS(std::runtime_error, read_initial_window(dir + "/side.csv", m), "side.meta.json: sidecar is not valid JSON (JSON: expected a key");
  const std::string meta = "{\"schema_version\": 1, \"states\": [{\"name\": \"color\", \"range\": [0, 44]}], "
                           "\"actions\": [{\"name\": \"angle\"}], \"run_id\": \"";
  write("side.meta.json", meta + "../x\"}");
  CHECK_THROWS(std::runtime_error, read_initial_window(dir + "/side.csv", m), "side.meta.json: run_id '../x' is not a plain name");
  write("side.meta.json", meta + "r7\"}");
  CHECK_THROWS(std::runtime_error, read_initial_window(dir + "/side.csv", m), "side.csv: row 3: column 'color' is 45, outside its valid range [0, 44]");
  write("side.meta.json", "{\"schema_version\": 1, \"states\": [{\"name\": \"color\"}], \"actions\": [{\"name\": \"angle\"}], \"run_id\": \"r7\", \"period_ms\": NaN}");
  CHECK_THROWS(std::runtime_error, read_initial_window(dir + "/side.csv", m), "sidecar is not valid JSON (NaN is not a value)");
  write("side.meta.json", "{\"schema_version\": 1, \"states\": [{\"name\": \"color\"}], \"actions\": [{\"name\": \"angle\"}], \"run_id\": \"r7\"}");
  CHECK(read_initial_window(dir + "/side.csv", m).run_id == "r7");
  CHECK_THROWS(std::runtime_error, read_sidecar(write("v2.meta.json", "{\"schema_version\": 2}")), "sidecar schema_version 2 is not supported");
  CHECK_THROWS(std::runtime_error, read_sidecar(write("src.meta.json", "{\"schema_version\": 1, \"source\": \"lab\"}")), "sidecar source \"lab\"");

  CHECK(is_run_id("log_30_0-sim1.x") && !is_run_id("") && !is_run_id(".hidden") && !is_run_id("a/b") && !is_run_id(std::string(121, 'a')));

  // the JSON reader keeps to JSON's grammar, as Python's json does (a sidecar both must refuse)
  for (const char* bad : {"01", "1.", ".5", "+1", "-", "1e", "\"a\nb\"", "[1,]"}) CHECK_THROWS(std::runtime_error, Json::parse(bad), "JSON");
  CHECK(Json::parse("-0.5e+2").number == -50 && Json::parse("1e999").number == INFINITY && Json::parse("1e-999").number == 0);
  CHECK(Json::parse("12").integer && !Json::parse("12.0").integer);

  // the JSON writer: null for a non-finite figure in strict output, Infinity kept, NaN never written
  CHECK(json_number(NAN) == "null" && json_number(INFINITY) == "null" && json_number(0.5) == "0.5");
  Json inf;
  inf.type = Json::Type::Number;
  inf.number = -INFINITY;
  CHECK(dump(inf) == "-Infinity");
  Json nan = inf;
  nan.number = NAN;
  CHECK_THROWS(std::invalid_argument, dump(nan), "NaN is not a value");
  CHECK_THROWS(std::invalid_argument, dump_indent1(nan), "NaN is not a value");

  std::system(("rm -rf " + dir).c_str());
  return failures();
}
