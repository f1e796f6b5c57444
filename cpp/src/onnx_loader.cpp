// ONNX -> Model. The file is read with a small protobuf wire-format decoder (see cpp/README.md for
// why not libprotobuf): every length is checked against the bytes that remain, every field of
// interest against its expected wire type, and only the handful of ONNX messages the model needs
// are decoded; unknown fields are skipped by their wire type, as protobuf itself does.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <iterator>
#include <map>
#include <set>

#include "envi/json.hpp"
#include "envi/dense.hpp"
#include "envi/model.hpp"
#include "envi/sha256.hpp"

namespace envi {
namespace {

constexpr int kMaxMessageDepth = 16;

// ---------------------------------------------------------------- wire format

struct Reader {
  const uint8_t* p;
  const uint8_t* end;

  bool done() const { return p >= end; }
  [[noreturn]] static void fail(const std::string& why) { throw ModelError("malformed ONNX file: " + why); }

  uint64_t varint() {
    uint64_t v = 0;
    for (int shift = 0; shift < 64; shift += 7) {
      if (p >= end) fail("truncated varint");
      uint8_t b = *p++;
      v |= uint64_t(b & 0x7F) << shift;
      if (!(b & 0x80)) return v;
    }
    fail("varint longer than 10 bytes");
  }
  Reader bytes() {
    uint64_t n = varint();
    if (n > uint64_t(end - p)) fail("length-delimited field runs past the end");
    Reader r{p, p + n};
    p += n;
    return r;
  }
  uint32_t fixed32() {
    if (end - p < 4) fail("truncated fixed32");
    uint32_t v;
    std::memcpy(&v, p, 4);
    p += 4;
    return v;
  }
  void skip(uint32_t wire) {
    switch (wire) {
      case 0: varint(); break;
      case 1: if (end - p < 8) fail("truncated fixed64"); p += 8; break;
      case 2: bytes(); break;
      case 5: fixed32(); break;
      default: fail("unsupported wire type " + std::to_string(wire));
    }
  }
  // Next field: returns false at the end; number and wire type out.
  bool next(uint32_t& field, uint32_t& wire) {
    if (done()) return false;
    uint64_t key = varint();
    field = uint32_t(key >> 3);
    wire = uint32_t(key & 7);
    if (field == 0 || (key >> 3) > 0x1FFFFFFF) fail("invalid field number");
    return true;
  }
  std::string str() {
    Reader r = bytes();
    return std::string(reinterpret_cast<const char*>(r.p), size_t(r.end - r.p));
  }
};

void expect(uint32_t wire, uint32_t want, const char* what) {
  if (wire != want) Reader::fail(std::string("field ") + what + " has the wrong wire type");
}

// ---------------------------------------------------------------- the ONNX messages we read

constexpr int32_t kFloat = 1, kInt64 = 7;  // TensorProto.DataType

struct Tensor {
  std::string name;
  std::vector<int64_t> dims;
  int32_t data_type = 0;
  std::vector<float> data;     // float32 tensors: the weights
  std::vector<int64_t> ints;   // int64 tensors: the residual head's indices and axes
  bool external = false;
};

struct Attribute {
  std::string name;
  int64_t i = 0;
  float f = 0.f;
  bool has_i = false, has_f = false, other = false;
};

struct Node {
  std::vector<std::string> inputs, outputs;
  std::string op, domain, name;
  std::vector<Attribute> attrs;
};

struct Graph {
  std::vector<Node> nodes;
  std::vector<Tensor> inits;
  std::vector<std::string> inputs, outputs;
  bool sparse = false;
};

void read_packed_or_single_int64(Reader& r, uint32_t wire, std::vector<int64_t>& out, const char* what) {
  if (wire == 0) { out.push_back(int64_t(r.varint())); return; }
  expect(wire, 2, what);
  Reader pr = r.bytes();
  while (!pr.done()) out.push_back(int64_t(pr.varint()));
}

Tensor read_tensor(Reader r) {
  Tensor t;
  std::vector<uint8_t> raw;
  bool has_raw = false;
  uint32_t f, w;
  while (r.next(f, w)) {
    switch (f) {
      case 1: read_packed_or_single_int64(r, w, t.dims, "dims"); break;
      case 2: expect(w, 0, "data_type"); t.data_type = int32_t(r.varint()); break;
      case 4:  // float_data, packed or not
        if (w == 5) { uint32_t u = r.fixed32(); float v; std::memcpy(&v, &u, 4); t.data.push_back(v); }
        else {
          expect(w, 2, "float_data");
          Reader pr = r.bytes();
          if ((pr.end - pr.p) % 4) Reader::fail("float_data length is not a multiple of 4");
          while (!pr.done()) { uint32_t u = pr.fixed32(); float v; std::memcpy(&v, &u, 4); t.data.push_back(v); }
        }
        break;
      case 7: read_packed_or_single_int64(r, w, t.ints, "int64_data"); break;
      case 8: expect(w, 2, "tensor name"); t.name = r.str(); break;
      case 9: { expect(w, 2, "raw_data"); Reader b = r.bytes(); raw.assign(b.p, b.end); has_raw = true; break; }
      case 13: t.external = true; r.skip(w); break;
      case 14: expect(w, 0, "data_location"); if (r.varint() != 0) t.external = true; break;
      default: r.skip(w);
    }
  }
  if (t.external) throw ModelError("initializer '" + t.name + "' uses external data; export with all weights inline");
  if (t.data_type != kFloat && t.data_type != kInt64)
    throw ModelError("initializer '" + t.name + "' is neither float32 nor int64 (data_type " + std::to_string(t.data_type) + ")");
  if (t.data_type == kFloat ? !t.ints.empty() : !t.data.empty())
    Reader::fail("initializer '" + t.name + "' holds values of another type than its data_type");
  uint64_t count = 1;
  for (int64_t d : t.dims) {
    if (d < 0 || d > (int64_t(1) << 31)) Reader::fail("initializer '" + t.name + "' has an invalid dimension");
    count *= uint64_t(d);
    if (count > (uint64_t(1) << 31)) Reader::fail("initializer '" + t.name + "' is too large");
  }
  const size_t width = t.data_type == kFloat ? 4 : 8;
  if (has_raw) {
    if (!t.data.empty() || !t.ints.empty()) Reader::fail("initializer '" + t.name + "' has both raw and typed data");
    if (raw.size() != count * width) Reader::fail("initializer '" + t.name + "' raw_data size does not match its shape");
    // little-endian, as ONNX specifies
    if (t.data_type == kFloat) t.data.resize(count);
    else t.ints.resize(count);
    if (count) std::memcpy(t.data_type == kFloat ? static_cast<void*>(t.data.data()) : static_cast<void*>(t.ints.data()),
                           raw.data(), raw.size());
  } else if ((t.data_type == kFloat ? t.data.size() : t.ints.size()) != count) {
    Reader::fail("initializer '" + t.name + "' has " + std::to_string(t.data_type == kFloat ? t.data.size() : t.ints.size()) +
                 " values, shape needs " + std::to_string(count));
  }
  return t;
}

Attribute read_attribute(Reader r) {
  Attribute a;
  uint32_t f, w;
  while (r.next(f, w)) {
    switch (f) {
      case 1: expect(w, 2, "attribute name"); a.name = r.str(); break;
      case 2: expect(w, 5, "attribute f"); { uint32_t u = r.fixed32(); std::memcpy(&a.f, &u, 4); a.has_f = true; } break;
      case 3: expect(w, 0, "attribute i"); a.i = int64_t(r.varint()); a.has_i = true; break;
      case 20: r.skip(w); break;  // type
      default: a.other = true; r.skip(w);  // strings, tensors, graphs, lists: no supported op needs them
    }
  }
  return a;
}

Node read_node(Reader r) {
  Node n;
  uint32_t f, w;
  while (r.next(f, w)) {
    switch (f) {
      case 1: expect(w, 2, "node input"); n.inputs.push_back(r.str()); break;
      case 2: expect(w, 2, "node output"); n.outputs.push_back(r.str()); break;
      case 3: expect(w, 2, "node name"); n.name = r.str(); break;
      case 4: expect(w, 2, "op_type"); n.op = r.str(); break;
      case 5: expect(w, 2, "attribute"); n.attrs.push_back(read_attribute(r.bytes())); break;
      case 7: expect(w, 2, "node domain"); n.domain = r.str(); break;
      default: r.skip(w);
    }
  }
  return n;
}

std::string value_info_name(Reader r) {
  std::string name;
  uint32_t f, w;
  while (r.next(f, w)) {
    if (f == 1) { expect(w, 2, "value name"); name = r.str(); }
    else r.skip(w);
  }
  return name;
}

Graph read_graph(Reader r) {
  Graph g;
  uint32_t f, w;
  while (r.next(f, w)) {
    switch (f) {
      case 1: expect(w, 2, "node"); g.nodes.push_back(read_node(r.bytes())); break;
      case 5: expect(w, 2, "initializer"); g.inits.push_back(read_tensor(r.bytes())); break;
      case 11: expect(w, 2, "graph input"); g.inputs.push_back(value_info_name(r.bytes())); break;
      case 12: expect(w, 2, "graph output"); g.outputs.push_back(value_info_name(r.bytes())); break;
      case 15: g.sparse = true; r.skip(w); break;
      default: r.skip(w);
    }
  }
  return g;
}

// ---------------------------------------------------------------- graph -> dense layers

const Attribute* attr(const Node& n, const char* name) {
  for (const auto& a : n.attrs)
    if (a.name == name) return &a;
  return nullptr;
}

// Each value of the graph is the input, or a chain of layers applied to another value.
struct Value {
  std::string parent;  // empty for the graph input
  std::vector<Dense> layers;
};

class Compiler {
 public:
  explicit Compiler(const Graph& g) : g_(g) {
    for (const auto& t : g.inits) {
      if (inits_.count(t.name)) throw ModelError("initializer '" + t.name + "' is defined twice");
      inits_[t.name] = &t;
    }
  }

  Model compile() {
    if (g_.sparse) throw ModelError("sparse initializers are not supported");
    std::vector<std::string> real_inputs;
    for (const auto& in : g_.inputs)
      if (!inits_.count(in)) real_inputs.push_back(in);
    if (real_inputs.size() != 1) throw ModelError("the model must have exactly one input, it has " + std::to_string(real_inputs.size()));
    values_[real_inputs[0]] = Value{};
    input_ = real_inputs[0];
    for (const auto& n : g_.nodes) {
      if (n.name.rfind(kResidualPrefix, 0) == 0) residual_.push_back(&n);  // checked against the metadata later
      else node(n);
    }
    if (g_.outputs.empty() || g_.outputs.size() > 3)
      throw ModelError("the model must have one output (mean), two (mean, log_std) or three (mean, log_std, event_logit), it has " +
                       std::to_string(g_.outputs.size()));
    Model m;
    auto mean = chain(mean_head());
    if (g_.outputs.size() == 1) {
      m.mean = std::move(mean);
    } else {
      auto ls = chain(g_.outputs[1]);
      size_t k = 0;  // shared prefix: the trunk (every head starts from the same value)
      while (k < mean.size() && k < ls.size() && prefix_[0][k] == prefix_[1][k]) ++k;
      m.trunk.assign(mean.begin(), mean.begin() + long(k));
      m.mean.assign(mean.begin() + long(k), mean.end());
      m.log_std.assign(ls.begin() + long(k), ls.end());
      if (m.mean.empty() || m.log_std.empty()) throw ModelError("the two outputs must be different heads");
      if (g_.outputs.size() == 3) {
        auto ev = chain(g_.outputs[2]);
        if (ev.size() <= k || !std::equal(prefix_[0].begin(), prefix_[0].begin() + long(k), prefix_[2].begin()))
          throw ModelError("the event output must be a head on the same trunk as the mean");
        m.event.assign(ev.begin() + long(k), ev.end());
      }
    }
    return m;
  }

  // Checks the residual.* nodes and initializers against what metadata 'envi.residual' implies
  // (the model `m` read from it): a residual head the metadata does not declare, or one that
  // differs from it in a single op, input, attribute or constant, is refused.
  void check_residual(const Model& m) const;

 private:
  static constexpr const char* kResidualPrefix = "residual.";
  const Graph& g_;
  std::map<std::string, const Tensor*> inits_;
  std::map<std::string, Value> values_;
  std::string input_;
  std::vector<std::vector<const Dense*>> prefix_;
  std::vector<const Node*> residual_;  // the residual head's nodes, in file order

  // The value the mean head's layers end in: the first output, or for a residual head what its
  // 'residual.change' node scales.
  std::string mean_head() const {
    if (residual_.empty()) return g_.outputs[0];
    for (const Node* n : residual_)
      if (n->name == "residual.change" && !n->inputs.empty()) return n->inputs[0];
    throw ModelError("the graph has residual nodes but no 'residual.change' scaling the mean head");
  }

  const Value& value(const std::string& name, const Node& n) {
    auto it = values_.find(name);
    if (it == values_.end()) throw ModelError(n.op + " node '" + n.name + "' reads '" + name + "', which no earlier node produces");
    return it->second;
  }
  // A float32 constant of a dense layer or a Clip. Its values must be finite (a Clip's bounds may be
  // infinite, as ONNX's own defaults are): a NaN weight passes every shape check and the content
  // hash alike, and would simulate NaN logs whose metrics count as steady.
  const Tensor& init(const std::string& name, const Node& n, bool infinite_ok = false) {
    auto it = inits_.find(name);
    if (it == inits_.end()) throw ModelError(n.op + " node '" + n.name + "': '" + name + "' must be a constant initializer");
    if (it->second->data_type != kFloat) throw ModelError(n.op + " node '" + n.name + "': '" + name + "' must be float32");
    for (float v : it->second->data)
      if (std::isnan(v) || (!infinite_ok && std::isinf(v)))
        throw ModelError("initializer '" + name + "' (read by " + n.op + " node '" + n.name + "') holds " +
                         (std::isnan(v) ? "NaN" : "inf") + ": a damaged model (re-export it with envi-export)");
    return *it->second;
  }
  // A layer's weights and bias after scaling and summing: finite inputs can still overflow.
  static void check_finite(const Dense& d, const Node& n) {
    if (!d.W.allFinite() || !d.b.allFinite())
      throw ModelError(n.op + " node '" + n.name + "': its weights or bias overflow to inf or NaN");
  }
  static void check_attrs(const Node& n, std::set<std::string> allowed) {
    for (const auto& a : n.attrs)
      if (!allowed.count(a.name) || a.other)
        throw ModelError(n.op + " node '" + n.name + "': attribute '" + a.name + "' is not supported");
  }
  void define(const Node& n, Value v) {
    if (n.outputs.size() != 1 || n.outputs[0].empty()) throw ModelError(n.op + " node '" + n.name + "' must have exactly one output");
    if (values_.count(n.outputs[0]) || inits_.count(n.outputs[0])) throw ModelError("value '" + n.outputs[0] + "' is defined twice");
    values_[n.outputs[0]] = std::move(v);
  }
  // A new value applying `d` to `in`: extend the chain when `in` is a fresh value.
  Value apply(const std::string& in, Dense d) {
    Value v{in, {}};
    v.layers.push_back(std::move(d));
    return v;
  }

  void node(const Node& n) {
    if (!n.domain.empty() && n.domain != "ai.onnx")
      throw ModelError("op '" + n.op + "' is from the foreign domain '" + n.domain + "'");
    if (n.op == "Gemm") gemm(n);
    else if (n.op == "MatMul") matmul(n);
    else if (n.op == "Add") add(n);
    else if (n.op == "Tanh" || n.op == "Relu" || n.op == "Sigmoid") activation(n);
    else if (n.op == "Clip") clip(n);
    else if (n.op == "Identity") { one_input(n); check_attrs(n, {}); define(n, Value{n.inputs[0], {}}); value(n.inputs[0], n); }
    else throw ModelError("op '" + n.op + "' (node '" + n.name + "') is not supported; the runtime runs Gemm, MatMul+Add, Tanh, Relu, Sigmoid, Clip");
  }
  static void one_input(const Node& n) {
    if (n.inputs.size() != 1) throw ModelError(n.op + " node '" + n.name + "' must have one input");
  }
  static Eigen::MatrixXf weight(const Tensor& t, bool trans, const Node& n) {
    if (t.dims.size() != 2) throw ModelError(n.op + " node '" + n.name + "': weight '" + t.name + "' is not a matrix");
    long rows = long(t.dims[0]), cols = long(t.dims[1]);
    if (rows < 1 || cols < 1) throw ModelError(n.op + " node '" + n.name + "': weight '" + t.name + "' is empty");
    // ONNX stores row-major (rows x cols); we keep W as out x in.
    Eigen::Map<const Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>> m(t.data.data(), rows, cols);
    if (trans) return m;  // B is (out x in) already
    return m.transpose();
  }
  static Eigen::VectorXf bias(const Tensor& t, long out, const Node& n) {
    size_t count = t.data.size();
    if (!(t.dims.size() == 1 || (t.dims.size() == 2 && t.dims[0] == 1)) || (long(count) != out && count != 1))
      throw ModelError(n.op + " node '" + n.name + "': bias '" + t.name + "' does not match the layer's " + std::to_string(out) + " outputs");
    Eigen::VectorXf b(out);
    for (long i = 0; i < out; ++i) b[i] = t.data[count == 1 ? 0 : size_t(i)];
    return b;
  }
  void gemm(const Node& n) {
    if (n.inputs.size() < 2 || n.inputs.size() > 3) throw ModelError("Gemm node '" + n.name + "' needs 2 or 3 inputs");
    check_attrs(n, {"alpha", "beta", "transA", "transB"});
    auto ai = [&](const char* k, int64_t d) { const Attribute* a = attr(n, k); return a && a->has_i ? a->i : d; };
    auto af = [&](const char* k, float d) { const Attribute* a = attr(n, k); return a && a->has_f ? a->f : d; };
    if (ai("transA", 0) != 0) throw ModelError("Gemm node '" + n.name + "': transA is not supported");
    for (const char* k : {"alpha", "beta"})
      if (!std::isfinite(af(k, 1.f))) throw ModelError("Gemm node '" + n.name + "': attribute '" + k + "' is not a finite number");
    value(n.inputs[0], n);
    Dense d;
    d.W = weight(init(n.inputs[1], n), ai("transB", 0) != 0, n) * af("alpha", 1.f);
    d.b = Eigen::VectorXf::Zero(d.W.rows());
    if (n.inputs.size() == 3 && !n.inputs[2].empty()) d.b = bias(init(n.inputs[2], n), d.W.rows(), n) * af("beta", 1.f);
    check_finite(d, n);
    define(n, apply(n.inputs[0], std::move(d)));
  }
  void matmul(const Node& n) {
    if (n.inputs.size() != 2) throw ModelError("MatMul node '" + n.name + "' needs 2 inputs");
    check_attrs(n, {});
    value(n.inputs[0], n);
    Dense d;
    d.W = weight(init(n.inputs[1], n), false, n);
    d.b = Eigen::VectorXf::Zero(d.W.rows());
    define(n, apply(n.inputs[0], std::move(d)));
  }
  void add(const Node& n) {
    if (n.inputs.size() != 2) throw ModelError("Add node '" + n.name + "' needs 2 inputs");
    check_attrs(n, {});
    bool first_const = inits_.count(n.inputs[0]) > 0;
    const std::string& x = n.inputs[first_const ? 1 : 0];
    const Value& v = value(x, n);
    // Only as the bias of a MatMul/Gemm whose result nothing else reads.
    if (v.layers.size() != 1 || v.layers[0].act != Act::None)
      throw ModelError("Add node '" + n.name + "' must add a constant bias to a MatMul or Gemm output");
    Value out = v;
    out.layers[0].b += bias(init(n.inputs[first_const ? 0 : 1], n), out.layers[0].W.rows(), n);
    check_finite(out.layers[0], n);
    define(n, std::move(out));
  }
  void set_act(const Node& n, Act act, float lo = 0.f, float hi = 0.f) {
    one_input(n);
    const Value& v = value(n.inputs[0], n);
    Dense d;
    d.act = act;
    d.clip_lo = lo;
    d.clip_hi = hi;
    Value out;
    if (v.layers.size() == 1 && v.layers[0].act == Act::None && v.layers[0].W.size()) {
      out = v;  // fuse into the preceding dense layer
      out.layers[0].act = act;
      out.layers[0].clip_lo = lo;
      out.layers[0].clip_hi = hi;
    } else {
      out = apply(n.inputs[0], std::move(d));  // activation alone: W stays empty
    }
    define(n, std::move(out));
  }
  void activation(const Node& n) {
    check_attrs(n, {});
    set_act(n, n.op == "Tanh" ? Act::Tanh : n.op == "Relu" ? Act::Relu : Act::Sigmoid);
  }
  float scalar(const std::string& name, const Node& n) {
    const Tensor& t = init(name, n, true);
    if (t.data.size() != 1) throw ModelError("Clip node '" + n.name + "': bound '" + name + "' is not a scalar");
    return t.data[0];
  }
  void clip(const Node& n) {
    if (n.inputs.empty() || n.inputs.size() > 3) throw ModelError("Clip node '" + n.name + "' needs 1 to 3 inputs");
    check_attrs(n, {});
    float lo = -INFINITY, hi = INFINITY;
    if (n.inputs.size() > 1 && !n.inputs[1].empty()) lo = scalar(n.inputs[1], n);
    if (n.inputs.size() > 2 && !n.inputs[2].empty()) hi = scalar(n.inputs[2], n);
    Node single = n;
    single.inputs.resize(1);
    set_act(single, Act::Clip, lo, hi);
  }

  // Layers from the input to `name`, remembering each layer's identity to find the shared trunk.
  std::vector<Dense> chain(const std::string& name) {
    std::vector<std::pair<const Value*, size_t>> order;
    std::string cur = name;
    size_t guard = 0;
    while (cur != input_) {
      auto it = values_.find(cur);
      if (it == values_.end()) throw ModelError("output '" + name + "' is not computed by the graph");
      order.push_back({&it->second, 0});
      cur = it->second.parent;
      if (++guard > values_.size()) throw ModelError("the graph has a cycle");
    }
    std::vector<Dense> out;
    std::vector<const Dense*> ids;
    for (auto r = order.rbegin(); r != order.rend(); ++r)
      for (const auto& d : r->first->layers) { out.push_back(d); ids.push_back(&d); }
    prefix_.push_back(std::move(ids));
    return out;
  }
};

// ---------------------------------------------------------------- residual head

// One node envi-export writes for a residual mean head (envi_py/export.py: _residual_base,
// _mean_output). An empty input stands for the mean head's output, whatever its name.
struct ResidualNode {
  std::string op, name, output;
  std::vector<std::string> inputs;
  std::map<std::string, int64_t> attrs;
};

// The constants those nodes read: float32 or int64, shape and values.
struct ResidualConst {
  std::string name;
  int32_t type;
  std::vector<int64_t> dims;
  std::vector<double> values;
};

std::string describe(const std::string& op, const std::vector<std::string>& inputs, const std::map<std::string, int64_t>& attrs) {
  std::string s = op + "(";
  for (size_t i = 0; i < inputs.size(); ++i) s += (i ? ", " : "") + (inputs[i].empty() ? std::string("<mean head>") : inputs[i]);
  for (const auto& [k, v] : attrs) s += ", " + k + "=" + std::to_string(v);
  return s + ")";
}

void Compiler::check_residual(const Model& m) const {
  const Model::Residual& r = m.residual;
  if (!r.on) {
    if (!residual_.empty())
      throw ModelError("graph node '" + residual_[0]->name +
                       "' belongs to a residual mean head, but metadata 'envi.residual' declares none");
    return;
  }
  const long l = m.history, c = m.channels(), ns = m.n_state();
  const std::string base = "residual.base";
  std::vector<ResidualNode> want;
  std::vector<ResidualConst> consts = {{"residual.scale", kFloat, {}, {r.scale}}, {"residual.axis", kInt64, {1}, {1}}};
  if (r.limits.empty()) {  // the last row's state columns
    want.push_back({"Slice", base, base, {input_, "residual.starts", "residual.ends", "residual.axis"}, {}});
    consts.push_back({"residual.starts", kInt64, {1}, {double((l - 1) * c)}});
    consts.push_back({"residual.ends", kInt64, {1}, {double((l - 1) * c + ns)}});
  } else {  // each state's last row in range: every row's state columns against per-state levels
    std::vector<double> levels(size_t(ns), INFINITY), index;
    for (const auto& lim : r.limits) levels[size_t(lim.state)] = lim.level;
    for (long t = 0; t < l; ++t)
      for (long i = 0; i < ns; ++i) index.push_back(double(t * c + i));
    consts.push_back({"residual.levels", kFloat, {ns}, levels});
    consts.push_back({"residual.tolerance", kFloat, {}, {r.tolerance}});
    consts.push_back({"residual.rows.index", kInt64, {l, ns}, index});
    want.push_back({"Gather", "residual.rows", "residual.rows", {input_, "residual.rows.index"}, {{"axis", 1}}});
    want.push_back({"Sub", "residual.offset", "residual.offset", {"residual.rows", "residual.levels"}, {}});
    want.push_back({"Abs", "residual.distance", "residual.distance", {"residual.offset"}, {}});
    want.push_back({"Greater", "residual.in_range", "residual.in_range", {"residual.distance", "residual.tolerance"}, {}});
    want.push_back({"Cast", "residual.in_range_float", "residual.in_range_float", {"residual.in_range"}, {{"to", kFloat}}});
    want.push_back({"ArgMax", "residual.last_in_range", "residual.last_in_range", {"residual.in_range_float"},
                    {{"axis", 1}, {"select_last_index", 1}}});
    want.push_back({"GatherElements", "residual.picked", "residual.picked", {"residual.rows", "residual.last_in_range"},
                    {{"axis", 1}}});
    want.push_back({"Squeeze", base, base, {"residual.picked", "residual.axis"}, {}});
  }
  want.push_back({"Mul", "residual.change", "residual.change", {"", "residual.scale"}, {}});
  want.push_back({"Add", "residual.add", g_.outputs[0], {"residual.change", base}, {}});

  const std::string why = " (metadata 'envi.residual' declares a residual mean head" +
                          std::string(r.limits.empty() ? "" : " with limit levels") + ")";
  std::set<std::string> seen;
  for (const Node* n : residual_) {
    if (!seen.insert(n->name).second) throw ModelError("graph node '" + n->name + "' appears twice" + why);
    for (const auto& out : n->outputs)
      if (values_.count(out) || inits_.count(out)) throw ModelError("value '" + out + "' is defined twice");
    auto it = std::find_if(want.begin(), want.end(), [&](const ResidualNode& w) { return w.name == n->name; });
    if (it == want.end()) throw ModelError("graph node '" + n->name + "' is not part of the residual mean head" + why);
    std::map<std::string, int64_t> attrs;
    bool plain_attrs = true;
    for (const auto& a : n->attrs) {
      attrs[a.name] = a.i;
      plain_attrs = plain_attrs && a.has_i && !a.has_f && !a.other;
    }
    std::vector<std::string> inputs = n->inputs;
    if (it->inputs.size() == inputs.size() && !inputs.empty() && it->inputs[0].empty()) inputs[0].clear();  // the mean head
    if (n->op != it->op || !(n->domain.empty() || n->domain == "ai.onnx") || inputs != it->inputs ||
        n->outputs != std::vector<std::string>{it->output} || attrs != it->attrs || !plain_attrs)
      throw ModelError("graph node '" + n->name + "' must be " + describe(it->op, it->inputs, it->attrs) + " -> " + it->output +
                       ", it is " + describe(n->op, inputs, attrs) + why);
  }
  for (const auto& w : want)
    if (!seen.count(w.name)) throw ModelError("the graph has no node '" + w.name + "'" + why);
  for (const auto& k : consts) {
    auto it = inits_.find(k.name);
    if (it == inits_.end()) throw ModelError("the graph has no initializer '" + k.name + "'" + why);
    const Tensor& t = *it->second;
    std::vector<double> got;
    if (t.data_type == kFloat) got.assign(t.data.begin(), t.data.end());
    else for (int64_t v : t.ints) got.push_back(double(v));
    bool same = t.data_type == k.type && t.dims == k.dims && got.size() == k.values.size();
    for (size_t i = 0; same && i < got.size(); ++i)
      same = k.type == kFloat ? float(got[i]) == float(k.values[i]) : got[i] == k.values[i];
    if (!same) throw ModelError("initializer '" + k.name + "' does not hold what metadata 'envi.residual' implies" + why);
  }
}

// ---------------------------------------------------------------- metadata

std::vector<ChannelInfo> channels(const Json& list) {
  std::vector<ChannelInfo> out;
  for (const auto& c : list.as_array()) {
    auto range = c.find("range") ? c.at("range").as_numbers() : std::vector<double>{-INFINITY, INFINITY};
    if (range.size() != 2) throw ModelError("channel range must be [low, high]");
    const Json* unit = c.find("unit");
    out.push_back({c.at("name").as_string(), unit ? unit->as_string() : "", range[0], range[1]});
  }
  return out;
}

using LayerKind = Model::EffectLayer::Kind;
// Each layer kind's name and unit, as envi_py.effect_layers.UNITS.
struct LayerKindName {
  const char* name;
  LayerKind kind;
  const char* unit;
};
constexpr LayerKindName kLayerKinds[] = {
    {"delay", LayerKind::Delay, "ticks"},          {"lag", LayerKind::Lag, "rows"},
    {"play", LayerKind::Play, "action units"},     {"gain_drift", LayerKind::GainDrift, "fraction"},
    {"run_gain", LayerKind::RunGain, "fraction"},  {"noise", LayerKind::Noise, "state units"},
    {"quantise", LayerKind::Quantise, "state units"}, {"saturation", LayerKind::Saturation, "state units"}};

// A number as Python's format(v, "g") writes it (six significant digits, the same rules as C's %g).
std::string g_format(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%g", v);
  return buf;
}

}  // namespace

std::string Model::EffectLayer::text() const {
  for (const auto& k : kLayerKinds)
    if (k.kind == kind)
      return kind == LayerKind::Saturation ? "saturation [" + g_format(low) + ", " + g_format(high) + "]"
                                           : std::string(k.name) + " " + g_format(value) + " " + k.unit;
  return "?";
}

std::string Model::describe_layers() const {
  std::string out;
  for (const auto& layer : layers) out += (out.empty() ? "" : ", ") + layer.text();
  return out.empty() ? "none" : out;
}

namespace {

// One entry of metadata 'envi.layers', checked as envi_py.effect_layers.Layer checks it.
Model::EffectLayer effect_layer(const Json& e) {
  using K = Model::EffectLayer::Kind;
  const std::string what = "metadata 'envi.layers': ";
  const Json* kind = e.type == Json::Type::Object ? e.find("kind") : nullptr;
  if (!kind || kind->type != Json::Type::String) throw ModelError(what + "each layer is an object with a 'kind'");
  Model::EffectLayer layer;
  bool known = false;
  for (const auto& k : kLayerKinds)
    if (kind->string == k.name) layer.kind = k.kind, known = true;
  if (!known) {
    std::string names;
    for (const auto& k : kLayerKinds) names += std::string(names.empty() ? "'" : ", '") + k.name + "'";
    throw ModelError(what + "unknown effect layer '" + kind->string + "'; known kinds: " + names);
  }
  auto number = [&](const char* key, double missing) {
    const Json* v = e.find(key);
    if (!v || v->is_null()) return missing;
    if (v->type != Json::Type::Number) throw ModelError(what + kind->string + ": '" + key + "' must be a number or null");
    return v->number;
  };
  layer.value = number("value", 0.0);
  layer.low = number("low", -INFINITY);
  layer.high = number("high", INFINITY);
  if (!std::isfinite(layer.value) || (layer.value < 0 && layer.kind != K::GainDrift))
    throw ModelError(what + kind->string + ": parameter must be finite and not negative");
  if (layer.kind == K::Delay && (layer.value != std::floor(layer.value) || layer.value > 1000))
    throw ModelError(what + "delay: a whole number of ticks up to 1000");
  if (layer.kind == K::Lag && layer.value > 1000)  // envi_py.effect_layers.MAX_LAG
    throw ModelError(what + "lag: a time constant up to 1000 rows");
  if ((layer.kind == K::GainDrift || layer.kind == K::RunGain) && std::fabs(layer.value) > 10)  // MAX_GAIN
    throw ModelError(what + "gain_drift and run_gain: a fraction of at most 10 in size");
  if (!(layer.low <= layer.high)) throw ModelError(what + kind->string + ": limits must be ordered numbers");
  return layer;
}

// A metadata value as an error message shows it: its JSON, shortened; never a second error.
std::string shown(const Json& v) {
  std::string text;
  try {
    text = dump(v);
  } catch (const std::exception&) {
    return "not a finite number";
  }
  return text.size() > 60 ? text.substr(0, 57) + "..." : text;
}

void read_metadata(Model& m) {
  std::map<std::string, Json> md;
  for (const auto& kv : m.metadata) {
    if (kv.first.rfind("envi.", 0) != 0) continue;
    try {
      md[kv.first] = Json::parse(kv.second);
    } catch (const std::exception& e) {
      throw ModelError("metadata '" + kv.first + "': " + e.what());
    }
  }
  auto get = [&](const char* k) -> const Json& {
    auto it = md.find(k);
    if (it == md.end()) throw ModelError(std::string("not an envi model: metadata '") + k + "' is missing (export with envi-export)");
    return it->second;
  };
  try {
    if (get("envi.format").as_string() != "envi-onnx") throw ModelError("metadata 'envi.format' is not 'envi-onnx'");
    // Enumerated entries: a value this loader does not know is refused, never read as a default.
    if (md.count("envi.format_version")) {
      const Json& v = md["envi.format_version"];
      if (!(v.type == Json::Type::Number && v.number == 1))
        throw ModelError("metadata 'envi.format_version' is " + shown(v) + "; known versions: 1 (update envi to read newer exports)");
    }
    {
      const Json& head = get("envi.head");
      static const char* const kHeads[] = {"deterministic", "gaussian"};
      if (head.type != Json::Type::String || (head.string != kHeads[0] && head.string != kHeads[1]))
        throw ModelError("metadata 'envi.head' is " + shown(head) + "; known heads: 'deterministic', 'gaussian'");
      if ((head.string == "gaussian") != m.gaussian())
        throw ModelError("metadata 'envi.head' is '" + head.string + "', but the graph " +
                         (m.gaussian() ? "has a log_std output" : "has no log_std output"));
    }
    const Json& schema = get("envi.schema");
    m.states = channels(schema.at("states"));
    m.actions = channels(schema.at("actions"));
    const Json& norm = get("envi.normaliser");
    m.norm_low = norm.at("low").as_numbers();
    m.norm_high = norm.at("high").as_numbers();
    double h = get("envi.history").as_number();
    if (!(h >= 1 && h <= 100000)) throw ModelError("metadata 'envi.history' is out of range");
    m.history = int(h);
    const Json& period = get("envi.period_ms");
    m.period_ms = period.is_null() ? 0.0 : period.as_number();
    if (!(std::isfinite(m.period_ms) && m.period_ms >= 0))
      throw ModelError("metadata 'envi.period_ms' must be null or a finite number >= 0");
    const Json& post = get("envi.post");
    if (post.at("clamp").type != Json::Type::Bool)
      throw ModelError("metadata 'envi.post': 'clamp' is " + shown(post.at("clamp")) + "; known values: true, false");
    m.clamp = post.at("clamp").boolean;
    for (const auto& lim : post.at("limits").as_array()) {
      auto lh = lim.as_numbers();
      if (lh.size() != 2) throw ModelError("metadata 'envi.post' limits must be [low, high] pairs");
      m.limit_low.push_back(lh[0]);
      m.limit_high.push_back(lh[1]);
    }
    if (!post.at("round_to").is_null()) m.round_to = post.at("round_to").as_numbers();
    if (md.count("envi.limit_events"))
      for (const auto& e : md["envi.limit_events"].as_array()) {
        auto iv = e.as_numbers();
        if (iv.size() != 2 || !(iv[0] >= 0 && iv[0] < double(m.states.size()) && iv[0] == std::floor(iv[0])) || !std::isfinite(iv[1]))
          throw ModelError("metadata 'envi.limit_events' must hold [state index, reading] pairs");
        m.limit_events.push_back({int(iv[0]), iv[1]});
      }
    if (md.count("envi.residual") && !md["envi.residual"].is_null()) {
      const Json& r = md["envi.residual"];
      double scale = r.at("scale").as_number(), tolerance = r.at("tolerance").as_number();
      if (!(std::isfinite(scale) && scale > 0 && std::isfinite(tolerance) && tolerance >= 0))
        throw ModelError("metadata 'envi.residual' needs a positive scale and a tolerance >= 0");
      m.residual = {true, float(scale), float(tolerance), {}};
      for (const auto& e : r.at("limit_levels").as_array()) {
        auto iv = e.as_numbers();
        if (iv.size() != 2 || !(iv[0] >= 0 && iv[0] < double(m.states.size()) && iv[0] == std::floor(iv[0])) || !std::isfinite(iv[1]))
          throw ModelError("metadata 'envi.residual' limit_levels must hold [state index, normalised level] pairs");
        m.residual.limits.push_back({int(iv[0]), float(iv[1])});
      }
    }
    if (md.count("envi.noise_dof") && !md["envi.noise_dof"].is_null()) {
      for (const Json& e : md["envi.noise_dof"].as_array()) {
        const double d = e.type == Json::Type::Number ? e.number : -1;
        if (!(d == 0 || (d >= 3 && d <= 30 && d == std::floor(d))))
          throw ModelError("metadata 'envi.noise_dof' must hold 0 (normal) or whole degrees of freedom 3..30 per state");
        m.noise_dof.push_back(int(d));
      }
      if (!m.noise_dof.empty() && m.noise_dof.size() != m.states.size())
        throw ModelError("metadata 'envi.noise_dof' must give one value per state");
    }
    if (md.count("envi.noise_mix") && !md["envi.noise_mix"].is_null()) {
      // envi_py.model.MAX_MIX_SHARE, MAX_MIX_SCALE
      const char* what = "metadata 'envi.noise_mix' must hold [0, 1] (none) or [p, k] with 0 < p < 0.5 and 1 < k <= 20 per state";
      for (const Json& e : md["envi.noise_mix"].as_array()) {
        if (e.type != Json::Type::Array || e.as_array().size() != 2) throw ModelError(what);
        for (const Json& v : e.as_array())
          if (v.type != Json::Type::Number) throw ModelError(what);
        auto pk = e.as_numbers();
        const bool none = pk[0] == 0 && pk[1] == 1, mixed = pk[0] > 0 && pk[0] < 0.5 && pk[1] > 1 && pk[1] <= 20;
        if (!none && !mixed) throw ModelError(what);
        m.noise_mix.push_back({pk[0], pk[1]});
      }
      if (!m.noise_mix.empty() && m.noise_mix.size() != m.states.size())
        throw ModelError("metadata 'envi.noise_mix' must give one [p, k] per state");
      for (size_t i = 0; i < m.noise_mix.size() && i < m.noise_dof.size(); ++i)
        if (m.noise_mix[i].first > 0 && m.noise_dof[i])
          throw ModelError("metadata 'envi.noise_mix' and 'envi.noise_dof' both shape state " + std::to_string(i));
    }
    if (md.count("envi.context") && !md["envi.context"].is_null()) {
      const Json& c = md["envi.context"];
      if (c.type != Json::Type::Bool) throw ModelError("metadata 'envi.context' must be true or false");
      m.context = c.boolean;
    }
    if (md.count("envi.layers") && !md["envi.layers"].is_null()) {
      const auto& entries = md["envi.layers"].as_array();
      if (entries.size() > 64)  // envi_py.effect_layers.MAX_LAYERS: each layer's draws are keyed by its index
        throw ModelError("metadata 'envi.layers': at most 64 layers, got " + std::to_string(entries.size()));
      for (const auto& e : entries) m.layers.push_back(effect_layer(e));
    }
    if (const Json* alg = md.count("envi.algorithm") ? &md["envi.algorithm"] : nullptr)
      if (alg->type == Json::Type::String) m.algorithm = alg->string;
  } catch (const ModelError&) {
    throw;
  } catch (const std::exception& e) {
    throw ModelError(std::string("envi metadata: ") + e.what());
  }
  size_t ns = m.states.size(), nc = ns + m.actions.size();
  if (ns == 0) throw ModelError("envi metadata: the schema has no states");
  if (m.norm_low.size() != nc || m.norm_high.size() != nc) throw ModelError("envi metadata: normaliser does not match the schema");
  for (size_t i = 0; i < nc; ++i)
    if (!(std::isfinite(m.norm_low[i]) && std::isfinite(m.norm_high[i]) && m.norm_high[i] > m.norm_low[i]))
      throw ModelError("metadata 'envi.normaliser': the range of channel " + std::to_string(i) + " ('" +
                       (i < ns ? m.states[i].name : m.actions[i - ns].name) + "') is empty or not finite");
  if (m.limit_low.size() != ns) throw ModelError("envi metadata: post-processing limits do not match the states");
  if (!m.round_to.empty() && m.round_to.size() != ns) throw ModelError("envi metadata: round_to does not match the states");
  for (double r : m.round_to)
    if (!(r > 0 && std::isfinite(r))) throw ModelError("envi metadata: round_to must be positive");
  // a residual head's limits are its limit events' (EnvModel.limit_levels): the same states, in order
  bool same = !m.residual.on || m.residual.limits.size() == m.limit_events.size();
  for (size_t k = 0; same && k < m.residual.limits.size(); ++k) same = m.residual.limits[k].state == m.limit_events[k].state;
  if (!same) throw ModelError("envi metadata: 'envi.residual' limit_levels must name the states of 'envi.limit_events', in order");
}

void check_shapes(const Model& m) {
  long width = m.in_features();
  auto walk = [&](const std::vector<Dense>& layers, long w, const char* what) {
    for (const auto& d : layers) {
      if (d.W.size() == 0) continue;
      if (d.W.cols() != w)
        throw ModelError(std::string(what) + ": a layer expects " + std::to_string(d.W.cols()) + " inputs but gets " + std::to_string(w));
      w = d.W.rows();
    }
    return w;
  };
  long t = walk(m.trunk, width, "trunk");
  if (walk(m.mean, t, "mean head") != m.n_state()) throw ModelError("the mean output does not have one value per state");
  if (m.gaussian() && walk(m.log_std, t, "log-std head") != m.n_state())
    throw ModelError("the log-std output does not have one value per state");
  if (m.event.empty() != m.limit_events.empty())
    throw ModelError("the event output and metadata 'envi.limit_events' must come together");
  if (!m.event.empty() && walk(m.event, t, "event head") != long(m.limit_events.size()))
    throw ModelError("the event output does not have one value per limit event");
  if (m.trunk.empty() && m.mean.empty()) throw ModelError("the model has no layers");
}

// Moves the first trunk layer's context columns to Model::context_W and its activation to a layer of
// its own (see Model::context): the engine adds the per-run context bias between the two.
void split_context(Model& m) {
  if (!m.context) return;
  if (m.trunk.empty() && m.mean.size() >= 2) {  // one head: its layers but the last become the trunk
    m.trunk.assign(m.mean.begin(), m.mean.end() - 1);
    m.mean.erase(m.mean.begin(), m.mean.end() - 1);
  }
  if (m.trunk.empty() || m.trunk[0].W.size() == 0)
    throw ModelError("metadata 'envi.context' needs a hidden layer to take the run context");
  Dense& first = m.trunk[0];
  const long window = m.window_features();
  m.context_W = first.W.rightCols(m.context_features());
  Eigen::MatrixXf w = first.W.leftCols(window);
  first.W = w;
  Dense act;
  act.act = first.act;
  act.clip_lo = first.clip_lo;
  act.clip_hi = first.clip_hi;
  first.act = Act::None;
  m.trunk.insert(m.trunk.begin() + 1, act);
}

// ---------------------------------------------------------------- content hash

constexpr const char* kHashKey = "envi.content_sha256";
constexpr const char* kReexport = " (re-export it with envi-export)";

// The canonical serialisation envi-export hashes (envi_py/export.py, content_sha256): the graph's
// inputs, outputs and nodes in file order, its initializers sorted by name (name, data type,
// shape, little-endian values) and the envi.* metadata but the hash itself sorted by key. Lengths
// and counts are little-endian u64, so no two different models serialise alike.
class Canonical {
 public:
  void u8(uint8_t v) { h_.update(&v, 1); }
  void u32(uint32_t v) { le(v, 4); }
  void u64(uint64_t v) { le(v, 8); }
  void str(const std::string& s) { u64(s.size()); h_.update(s); }
  void strs(const std::vector<std::string>& v) {
    u64(v.size());
    for (const auto& s : v) str(s);
  }
  std::string hex() { return h_.hex(); }

 private:
  void le(uint64_t v, int n) {
    uint8_t b[8];
    for (int i = 0; i < n; ++i) b[i] = uint8_t(v >> (8 * i));
    h_.update(b, size_t(n));
  }
  Sha256 h_;
};

using Metadata = std::vector<std::pair<std::string, std::string>>;

std::string content_digest(const Graph& g, const Metadata& metadata) {
  Canonical c;
  c.str("envi-content-v1");
  c.strs(g.inputs);
  c.strs(g.outputs);
  c.u64(g.nodes.size());
  for (const Node& n : g.nodes) {
    c.str(n.op);
    c.str(n.domain);
    c.str(n.name);
    c.strs(n.inputs);
    c.strs(n.outputs);
    c.u64(n.attrs.size());
    for (const Attribute& a : n.attrs) {
      c.str(a.name);
      c.u8(a.has_i);
      if (a.has_i) c.u64(uint64_t(a.i));
      c.u8(a.has_f);
      if (a.has_f) { uint32_t u; std::memcpy(&u, &a.f, 4); c.u32(u); }
    }
  }
  std::vector<const Tensor*> inits;
  for (const Tensor& t : g.inits) inits.push_back(&t);
  std::stable_sort(inits.begin(), inits.end(), [](const Tensor* a, const Tensor* b) { return a->name < b->name; });
  c.u64(inits.size());
  for (const Tensor* t : inits) {
    c.str(t->name);
    c.u32(uint32_t(t->data_type));
    c.u64(t->dims.size());
    for (int64_t d : t->dims) c.u64(uint64_t(d));
    if (t->data_type == kInt64) {
      c.u64(t->ints.size() * 8);
      for (int64_t v : t->ints) c.u64(uint64_t(v));
    } else {
      c.u64(t->data.size() * 4);
      for (float v : t->data) { uint32_t u; std::memcpy(&u, &v, 4); c.u32(u); }
    }
  }
  Metadata md;
  for (const auto& kv : metadata)
    if (kv.first.rfind("envi.", 0) == 0 && kv.first != kHashKey) md.push_back(kv);
  std::sort(md.begin(), md.end());
  c.u64(md.size());
  for (const auto& kv : md) {
    c.str(kv.first);
    c.str(kv.second);
  }
  return c.hex();
}

// A flipped weight or an edited entry must not run silently: the file's hash must match its content.
void verify_content_hash(const Graph& g, const Metadata& metadata) {
  const std::string* stored = nullptr;
  for (const auto& kv : metadata) {
    if (kv.first != kHashKey) continue;
    if (stored) throw ModelError(std::string("metadata '") + kHashKey + "' is given twice" + kReexport);
    stored = &kv.second;
  }
  if (!stored)
    throw ModelError(std::string("no content hash ('") + kHashKey + "'): the file was exported by an envi older than "
                     "its content check, or edited" + kReexport);
  std::string want;
  try {
    Json j = Json::parse(*stored);
    if (j.type == Json::Type::String) want = j.string;
  } catch (const std::exception&) {
  }
  if (want.size() != 64 || want.find_first_not_of("0123456789abcdef") != std::string::npos)
    throw ModelError(std::string("metadata '") + kHashKey + "' is not a SHA-256 hex digest" + kReexport);
  if (content_digest(g, metadata) != want)
    throw ModelError(std::string("content hash mismatch: the file was changed after export") + kReexport);
}

// The wire-level parts of a ModelProto.
struct File {
  Graph graph;
  bool has_graph = false;
  int64_t opset = -1;
  Metadata metadata;
};

File parse_file(const uint8_t* data, size_t size) {
  Reader r{data, data + size};
  File file;
  uint32_t f, w;
  while (r.next(f, w)) {
    switch (f) {
      case 7: expect(w, 2, "graph"); file.graph = read_graph(r.bytes()); file.has_graph = true; break;
      case 8: {  // opset_import
        expect(w, 2, "opset_import");
        Reader o = r.bytes();
        std::string domain;
        int64_t version = 0;
        uint32_t of, ow;
        while (o.next(of, ow)) {
          if (of == 1) { expect(ow, 2, "opset domain"); domain = o.str(); }
          else if (of == 2) { expect(ow, 0, "opset version"); version = int64_t(o.varint()); }
          else o.skip(ow);
        }
        if (!domain.empty() && domain != "ai.onnx") throw ModelError("the model imports the foreign operator set '" + domain + "'");
        file.opset = version;
        break;
      }
      case 14: {  // metadata_props
        expect(w, 2, "metadata_props");
        Reader e = r.bytes();
        std::string k, v;
        uint32_t ef, ew;
        while (e.next(ef, ew)) {
          if (ef == 1) { expect(ew, 2, "metadata key"); k = e.str(); }
          else if (ef == 2) { expect(ew, 2, "metadata value"); v = e.str(); }
          else e.skip(ew);
        }
        file.metadata.emplace_back(std::move(k), std::move(v));
        break;
      }
      case 25: throw ModelError("the model defines local functions, which are not supported");
      default: r.skip(w);
    }
  }
  if (!file.has_graph) throw ModelError("not an ONNX model: no graph");
  return file;
}

}  // namespace

std::string content_sha256(const uint8_t* data, size_t size) {
  File file = parse_file(data, size);
  return content_digest(file.graph, file.metadata);
}

std::string Model::metadata_value(const std::string& key) const {
  for (const auto& kv : metadata)
    if (kv.first == key) return kv.second;
  return "null";
}

int Model::max_width() const {
  long w = in_features();
  for (const auto* layers : {&trunk, &mean, &log_std, &event})
    for (const auto& d : *layers) w = std::max<long>(w, d.W.rows());
  return int(w);
}

Model load_model(const uint8_t* data, size_t size) {
  File file = parse_file(data, size);
  if (file.opset < 7 || file.opset > 21) throw ModelError("unsupported or missing default opset version " + std::to_string(file.opset));
  Compiler compiler(file.graph);
  Model m = compiler.compile();
  m.metadata = file.metadata;
  read_metadata(m);
  compiler.check_residual(m);
  check_shapes(m);
  // Last, so that a file broken in structure is named by what is wrong with it (and fuzzing
  // reaches every check above); what passes them must still be the file that was exported.
  verify_content_hash(file.graph, file.metadata);
  split_context(m);
  for (auto* layers : {&m.trunk, &m.mean, &m.log_std, &m.event})
    for (Dense& d : *layers)
      if (PackedDense::suits(d)) d.packed = std::make_shared<const PackedDense>(d);
  return m;
}

Model load_model_file(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw ModelError(path + ": cannot open");
  std::vector<uint8_t> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  try {
    return load_model(bytes.data(), bytes.size());
  } catch (const ModelError& e) {
    throw ModelError(path + ": " + e.what());
  }
}

}  // namespace envi
