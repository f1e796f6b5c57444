// An exported envi model compiled to a plain list of dense layers, plus what the closed loop needs
// from the file's metadata (normalisation, history, post-processing, schema).
#pragma once
#include <Eigen/Core>
#include <cmath>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

namespace envi {

// Any problem with a model file: unsupported op, foreign domain, external data, malformed bytes.
struct ModelError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

enum class Act { None, Tanh, Relu, Sigmoid, Clip };

class PackedDense;  // envi/dense.hpp

// y = act(W x + b) on column vectors (one column per simulation).
struct Dense {
  Eigen::MatrixXf W;  // out x in
  Eigen::VectorXf b;  // out
  Act act = Act::None;
  float clip_lo = 0.f, clip_hi = 0.f;
  // The same layer packed for the engine's microkernel, made once at load where it suits.
  std::shared_ptr<const PackedDense> packed;
};

struct ChannelInfo {
  std::string name, unit;
  double low, high;
};

struct Model {
  std::vector<Dense> trunk;    // shared layers
  std::vector<Dense> mean;     // mean head (after the trunk)
  std::vector<Dense> log_std;  // empty for a deterministic model
  std::vector<Dense> event;    // limit-event logits (after the trunk); empty without events

  // A saturating sensor's jump to its limit, predicted as an event: the next reading of state
  // `state` is `value` with probability sigmoid(logit), whatever the Gaussian drew.
  struct LimitEvent {
    int state;
    double value;
  };
  std::vector<LimitEvent> limit_events;

  // A residual mean head (metadata 'envi.residual'): mean = scale * (mean head) + base, the base
  // being each state's last reading in the window (normalised), and for a state with a limit its
  // last reading farther than `tolerance` from `level` (the last reading when none is).
  struct Residual {
    bool on = false;
    float scale = 0.f, tolerance = 0.f;
    struct Limit {
      int state;
      float level;  // the limit event's reading, normalised
    };
    std::vector<Limit> limits;
  };
  Residual residual;

  // Effect layers around the learnt model (metadata 'envi.layers'; the Python twin is
  // envi_py.effect_layers.LayerStack), applied in order. Action layers change what the model sees of
  // the commands (delay of k ticks, first-order lag of tau rows, play of a full width, a gain drifting
  // linearly over the run, a gain per run of sd `value`); state layers change what the controller and
  // the log see of the predicted states (Gaussian noise of sd `value`, a quantisation step, clipping
  // to [low, high]). The model's own window keeps its prediction and sees the layered commands.
  struct EffectLayer {
    enum class Kind { Delay, Lag, Play, GainDrift, RunGain, Noise, Quantise, Saturation };
    Kind kind = Kind::Delay;
    double value = 0.0;
    double low = -INFINITY, high = INFINITY;
    // As envi_py.effect_layers.Layer.text says it: 'delay 2 ticks', 'saturation [0, 20]'.
    std::string text() const;
  };
  std::vector<EffectLayer> layers;
  // The layers in one phrase, as envi_py.effect_layers.describe: 'delay 2 ticks, noise 1.5 state units'.
  std::string describe_layers() const;

  // The Gaussian head's step-noise shape per state (metadata 'envi.noise_dof'; empty: all normal):
  // 0 is a normal draw, nu >= 3 a Student-t of nu degrees of freedom scaled to unit variance.
  std::vector<int> noise_dof;
  // Or, per state, a two-scale normal (metadata 'envi.noise_mix'; empty: none): {p, k} draws a share
  // p of steps at k times the scale of the rest, scaled to unit variance; {0, 1} leaves the state to noise_dof.
  std::vector<std::pair<double, double>> noise_mix;

  // A run context (metadata 'envi.context'; envi_py.dataset.context_of): the network's input ends
  // with each state's mean and population sd over sigma_0's l normalised rows, fixed for the run. At
  // load the first trunk layer's columns for it move to `context_W` and that layer's activation to a
  // layer of its own, so the engine adds context_W * context (a per-run bias) before it.
  bool context = false;
  Eigen::MatrixXf context_W;  // first trunk layer's width x 2 n_state

  // From metadata_props.
  std::vector<ChannelInfo> states, actions;
  std::vector<double> norm_low, norm_high;  // per logged channel (states then actions)
  int history = 0;
  double period_ms = 0.0;  // 0 when unknown
  bool clamp = true;
  std::vector<double> limit_low, limit_high;  // per state
  std::vector<double> round_to;               // per state; empty: no rounding
  std::string algorithm;
  std::vector<std::pair<std::string, std::string>> metadata;  // every key/value, as stored

  int n_state() const { return int(states.size()); }
  int n_action() const { return int(actions.size()); }
  int channels() const { return n_state() + n_action(); }
  int window_features() const { return history * channels(); }
  int context_features() const { return context ? 2 * n_state() : 0; }
  int in_features() const { return window_features() + context_features(); }
  bool gaussian() const { return !log_std.empty(); }
  int max_width() const;
  // The stored text (JSON) of metadata `key`, "null" when the file has none.
  std::string metadata_value(const std::string& key) const;
};

// Parse and compile an ONNX file's bytes; throws ModelError.
Model load_model(const uint8_t* data, size_t size);
Model load_model_file(const std::string& path);

// The content hash envi-export stores as 'envi.content_sha256' (hex), computed from the file's
// graph, initializers and envi.* metadata; load_model refuses a file whose stored hash differs.
std::string content_sha256(const uint8_t* data, size_t size);

}  // namespace envi
