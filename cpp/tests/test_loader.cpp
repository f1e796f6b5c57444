// The ONNX loader: what it accepts, and a clear ModelError for everything else, including every
// truncation of a valid file.
#include "check.hpp"
#include "envi/model.hpp"
#include "onnx_builder.hpp"

using envi::ModelError;

static envi::Model load(const pb::Bytes& b) { return envi::load_model(reinterpret_cast<const uint8_t*>(b.data()), b.size()); }

int main() {
  pb::Spec spec;
  envi::Model m = load(pb::model(spec));
  CHECK(m.history == 3 && m.n_state() == 1 && m.n_action() == 1 && !m.gaussian());
  CHECK(m.trunk.empty() && m.mean.size() == 2);
  CHECK(m.mean[0].W.rows() == 8 && m.mean[0].W.cols() == 6 && m.mean[0].act == envi::Act::Tanh);
  CHECK(m.mean[1].W.rows() == 1 && m.mean[1].act == envi::Act::Tanh);
  CHECK(m.states[0].name == "color" && m.actions[0].unit == "deg" && m.algorithm == "bc");

  spec.gaussian = true;
  envi::Model g = load(pb::model(spec));
  CHECK(g.gaussian() && g.trunk.size() == 1 && g.mean.size() == 1 && g.log_std.size() == 1);
  CHECK(g.log_std[0].act == envi::Act::Clip && g.log_std[0].clip_lo == -7.f && g.log_std[0].clip_hi == 1.f);
  CHECK(g.log_std[0].b[0] == -1.5f);  // MatMul + Add fused into one dense layer

  spec.gaussian = false;
  CHECK_THROWS(ModelError, load(pb::model(spec, {pb::node("Softmax", {"mean"}, "z")})), "Softmax");
  CHECK_THROWS(ModelError, load(pb::model(spec, {pb::node("Tanh", {"mean"}, "z", {}, "com.example")})), "foreign domain");
  CHECK_THROWS(ModelError, load(pb::model(spec, {pb::node("Tanh", {"nowhere"}, "z")})), "no earlier node");
  CHECK_THROWS(ModelError, load(pb::model(spec, {pb::node("Tanh", {"mean"}, "a0")})), "defined twice");
  spec.post = R"({"clamp": true, "limits": [], "round_to": null})";
  CHECK_THROWS(ModelError, load(pb::model(spec)), "limits");
  spec.post = R"({"clamp": true, "limits": [[0, 100]], "round_to": [0]})";
  CHECK_THROWS(ModelError, load(pb::model(spec)), "round_to");
  spec.post = R"({"clamp": tru)";
  CHECK_THROWS(ModelError, load(pb::model(spec)), "envi.post");
  spec.post = R"({"clamp": "yes", "limits": [[0, 100]], "round_to": null})";  // not read as false
  CHECK_THROWS(ModelError, load(pb::model(spec)), "metadata 'envi.post': 'clamp' is \"yes\"; known values: true, false");
  spec = pb::Spec{};

  // Non-finite weights pass the shape checks and the content hash (made over them): refused by name.
  spec.gaussian = true;
  for (const char* name : {"w0", "b0", "w1", "b1", "w2", "b2"}) {
    spec.bad_initializer = name;
    const std::string message = "initializer '" + std::string(name) + "' (read by";
    CHECK_THROWS(ModelError, load(pb::model(spec)), message.c_str());
    spec.bad_value = INFINITY;
    CHECK_THROWS(ModelError, load(pb::model(spec)), message.c_str());
    spec.bad_value = NAN;
  }
  spec.bad_initializer = "lo";  // a Clip bound may be infinite, never NaN
  CHECK_THROWS(ModelError, load(pb::model(spec)), "initializer 'lo' (read by Clip node");
  spec.bad_value = -INFINITY;
  CHECK(load(pb::model(spec)).log_std[0].clip_lo == -INFINITY);
  spec.bad_initializer.clear();
  spec.bad_value = NAN;

  // envi.head: one of the known heads, and the one the graph has
  spec.head_meta = "\"laplace\"";
  CHECK_THROWS(ModelError, load(pb::model(spec)), "metadata 'envi.head' is \"laplace\"; known heads: 'deterministic', 'gaussian'");
  spec.head_meta = "null";
  CHECK_THROWS(ModelError, load(pb::model(spec)), "metadata 'envi.head' is null; known heads");
  spec.head_meta = "\"deterministic\"";
  CHECK_THROWS(ModelError, load(pb::model(spec)), "metadata 'envi.head' is 'deterministic', but the graph has a log_std output");
  spec.gaussian = false;
  spec.head_meta = "\"gaussian\"";
  CHECK_THROWS(ModelError, load(pb::model(spec)), "metadata 'envi.head' is 'gaussian', but the graph has no log_std output");
  spec = pb::Spec{};

  // external data: data_location = EXTERNAL on an initializer
  pb::Bytes ext = pb::model(spec);
  pb::Bytes t = pb::tensor("w9", {1}, {1.f});
  pb::field_int(t, 14, 1);
  pb::Bytes graph;
  pb::field_bytes(graph, 5, t);
  pb::Bytes wrapper;
  pb::field_bytes(wrapper, 7, graph);  // a second graph field: the loader reads it too
  CHECK_THROWS(ModelError, load(ext + wrapper), "external data");

  // The content hash: a flipped weight bit, an edited metadata value, a missing or malformed hash.
  const pb::Bytes exported = pb::model(spec);
  CHECK(exported.find("envi.content_sha256") != pb::Bytes::npos);
  size_t w0 = exported.find(pb::Bytes("\x42\x02w0\x4a", 5));  // name "w0", then raw_data's key
  CHECK(w0 != pb::Bytes::npos);
  pb::Bytes flipped = exported;
  flipped[w0 + 5 + 2] ^= 1;  // past the two-byte length: the lowest mantissa bit of w0[0]
  CHECK_THROWS(ModelError, load(flipped), "content hash mismatch: the file was changed after export (re-export it with envi-export)");
  pb::Bytes edited = exported;
  size_t period = edited.find("40.0");
  CHECK(period != pb::Bytes::npos);
  edited[period + 1] = '1';  // envi.period_ms 41.0: a valid model, not the exported one
  CHECK_THROWS(ModelError, load(edited), "content hash mismatch");
  spec.hash = false;
  CHECK_THROWS(ModelError, load(pb::model(spec)), "no content hash");
  pb::Bytes bad_hash = pb::model(spec);
  pb::Bytes entry;
  pb::field_bytes(entry, 1, "envi.content_sha256");
  pb::field_bytes(entry, 2, "\"abc\"");
  pb::field_bytes(bad_hash, 14, entry);
  CHECK_THROWS(ModelError, load(bad_hash), "not a SHA-256 hex digest");
  pb::Bytes twice = exported;
  pb::field_bytes(twice, 14, entry);
  CHECK_THROWS(ModelError, load(twice), "given twice");
  spec = pb::Spec{};
  const uint8_t* ep = reinterpret_cast<const uint8_t*>(exported.data());
  CHECK(envi::content_sha256(ep, exported.size()) == envi::content_sha256(ep, exported.size()));
  CHECK(envi::content_sha256(ep, exported.size()) !=
        envi::content_sha256(reinterpret_cast<const uint8_t*>(flipped.data()), flipped.size()));

  CHECK_THROWS(ModelError, load(""), "no graph");
  CHECK_THROWS(ModelError, load(pb::Bytes(16, '\xff')), "malformed");
  const pb::Bytes good = pb::model(spec);
  int clear = 0;
  for (size_t n = 0; n < good.size(); ++n) {
    try {
      load(good.substr(0, n));
    } catch (const ModelError&) {
      ++clear;
    }
  }
  CHECK(clear == int(good.size()));  // every proper prefix is rejected with a ModelError
  std::printf("test_loader: %d failure(s)\n", failures());
  return failures() ? 1 : 0;
}
