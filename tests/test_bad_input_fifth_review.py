"""Regressions of the fifth bad-input review (stop 43). Each input here once ended in a traceback,
replaced a file the command had read, or passed silently into wrong results. Each must now be one
line naming the file or option, exit code 2, with nothing already written touched."""

from __future__ import annotations

import json

from pathlib import Path

import pytest

from envi_py.controllers import ControllerSpec
from envi_py.files import MAX_DEPTH, parse_json, parse_toml
from envi_py.goals.requirements import MAX_EXPR, RequirementSpec, parse
from envi_py.model import Checkpoint, ModelConfig
from envi_py.system import pattern_regex
from envi_py.twin import generate, write_logs
from tests.test_bad_input_audit import assert_one_line, run_cli
from tests.test_bad_input_fourth_review import description
from tests.test_export import paper_ckpt

HUGE = "1" + "0" * 400  # an integer no float holds


def plain_logs(folder: Path, period: int = 40, x: int = 30, runs: int = 3, rows: int = 30) -> Path:
    """Lane-keeping logs without sidecars (as the real ones), ``period`` ms apart."""
    folder.mkdir(parents=True, exist_ok=True)
    for run in range(runs):
        body = "".join(f"{i * period},{20 + (7 * i + run) % 50},{x if i % 4 < 2 else -x}\n" for i in range(rows))
        (folder / f"log_{x}_{run}.csv").write_text("time,color,angle\n" + body)
    return folder


def simulate(model: Path, logs: Path, out: Path, *extra: str) -> tuple[int, str]:
    """``envi simulate`` of ``model`` from the plain logs in ``logs`` into ``out``: exit code, stderr."""
    argv = ["simulate", "--model", str(model), "--init-logs", str(logs), "--pattern", "log_{x}_{run}.csv"]
    return run_cli([*argv, "--out", str(out), *extra])


def split(out: Path, *sources_and_options: str) -> tuple[int, str]:
    """``envi split`` of plain logs (named by the lane-keeping pattern) into ``out``: exit code, stderr."""
    return run_cli(["split", "--logs", *sources_and_options, "--pattern", "log_{x}_{run}.csv", "--out", str(out)])


def test_a_symbolic_link_loop_among_the_logs_is_named(tmp_path):
    logs = plain_logs(tmp_path / "logs")
    loop = logs / "log_30_9.csv"
    loop.symlink_to(loop)
    code, err = split(tmp_path / "s", str(logs))
    assert "loops" in assert_one_line(code, err, "split", loop)


@pytest.mark.parametrize(
    ("text", "parse", "said"),
    [
        ('{"a": ' + HUGE + "}", parse_json, "an integer too large for a number"),
        ("a = " + HUGE + "\n", parse_toml, "an integer too large for a number"),
        ('{"a": ' + "[" * (MAX_DEPTH + 1) + "]" * (MAX_DEPTH + 1) + "}", parse_json, "nested deeper than 32"),
        ("a = " + "[" * 3000 + "]" * 3000 + "\n", parse_toml, "nested too deeply"),
        ('{"a": ' + "[" * 3000 + "]" * 3000 + "}", parse_json, "nested too deeply"),
    ],
)
def test_json_and_toml_inputs_refuse_huge_integers_and_deep_nesting(text, parse, said):
    with pytest.raises(ValueError, match=said) as err:
        parse(text, "in.txt", "an input")
    assert str(err.value).startswith("in.txt: ")


def test_every_reader_of_json_and_toml_uses_the_checks(tmp_path):
    """A description, a run file, a layers file and a sidecar each once raised OverflowError or
    RecursionError from the code that read them; now each is one line naming the file."""
    logs = plain_logs(tmp_path / "logs")
    out = str(tmp_path / "out")
    system = description(tmp_path, period=HUGE)
    code, err = run_cli(["split", "--logs", str(logs), "--system", str(system), "--out", out])
    assert "too large" in assert_one_line(code, err, "split", system)
    deep = tmp_path / "deep.toml"
    deep.write_text("a = " + "[" * 2000 + "]" * 2000 + "\n")
    code, err = run_cli(["--config", str(deep), "split"])
    assert code == 2 and err.strip() == f"envi: error: {deep}: a run file is not valid TOML (nested too deeply)", err
    layers = tmp_path / "layers.json"
    layers.write_text('{"layers": [{"layer": {"kind": "noise", "value": ' + HUGE + "}}]}")
    model = paper_ckpt("gaussian").save(tmp_path / "m.pt")
    code, err = simulate(model, logs, Path(out), "--layers", str(layers))
    assert "too large" in assert_one_line(code, err, "simulate", layers)
    side = logs / "log_30_0.meta.json"
    side.write_text('{"schema_version": ' + HUGE + "}")
    code, err = run_cli(["split", "--logs", str(logs), "--out", out])
    assert "too large" in assert_one_line(code, err, "split", side)
    assert not Path(out).exists()


def test_a_requirement_nested_too_deeply_or_too_long_is_refused():
    deep = RequirementSpec("deep", "max_abs_dev(color, 40) <= " + "-" * 1500 + "35")
    with pytest.raises(ValueError, match="requirement 'deep': the expression is nested too deeply"):
        parse(deep, ["color"])
    long = RequirementSpec("long", "always " * 300 + "(color >= 10)", kind="stl")
    with pytest.raises(ValueError, match=f"requirement 'long': 2113 characters, at most {MAX_EXPR}"):
        parse(long, ["color"])


def test_init_never_replaces_a_log_it_drafts_from(tmp_path):
    logs = plain_logs(tmp_path / "logs")
    target = logs / "log_30_1.csv"
    before = target.read_bytes()
    code, err = run_cli(["init", "--logs", str(logs), "-o", str(target), "--force"])
    assert "is an input of this command" in assert_one_line(code, err, "init", target)
    assert target.read_bytes() == before


def test_a_pattern_whose_fields_touch_is_refused():
    """'log_{x}{run}.csv' read log_30_1.csv as x = 3, run '0_1', and simulated controller x = 3."""
    with pytest.raises(ValueError, match=r"fields \{x\}\{run\} touch"):
        pattern_regex("log_{x}{run}.csv")
    assert pattern_regex("log_{x}_{run}.csv").match("log_30_1.csv").groupdict() == {"x": "30", "run": "1"}


def test_train_refuses_an_onnx_name_and_a_checkpoint_named_onnx_still_loads(tmp_path):
    logs = plain_logs(tmp_path / "logs")
    out = tmp_path / "m.onnx"
    code, err = run_cli(["train", "--logs", str(logs), "--pattern", "log_{x}_{run}.csv", "-o", str(out)])
    assert "names an exported model" in assert_one_line(code, err, "train", out)
    assert not out.exists()
    renamed = paper_ckpt("gaussian").save(tmp_path / "ck.pt").rename(tmp_path / "ck.onnx")
    assert Checkpoint.load(renamed).config.head == "gaussian"  # torch's zip, whatever its name


def test_the_weight_bound_counts_the_input_layer():
    """history 10000 with one hidden layer of 100000 passed (no weights *between* hidden layers) and
    asked for 2e9 weights at the first step."""
    with pytest.raises(ValueError, match="2,000,000,000 weights, more than 50,000,000"):
        ModelConfig(n_state=1, n_action=1, history=10_000, hidden=(100_000,))
    ModelConfig(n_state=1, n_action=1, history=10_000, hidden=(256,))  # 5 M weights: fine


def test_plain_logs_of_another_period_than_the_description_are_refused(tmp_path):
    """80 ms logs beside 40 ms ones were split, verified and simulated as 40 ms ones."""
    logs = plain_logs(tmp_path / "a")
    slow = plain_logs(tmp_path / "b", period=80, x=50)
    code, err = split(tmp_path / "s", str(logs), str(slow))
    line = assert_one_line(code, err, "split", slow / "log_50_0.csv")
    assert "rows are 80 ms apart (median), but the system description 'lane-keeping' says a 40 ms period" in line
    code, err = split(tmp_path / "s", str(plain_logs(tmp_path / "c", period=41)))
    assert code == 0, err  # the real robot's 41 ms rows are its 40 ms loop


def test_simulate_refuses_a_log_of_the_window_alone(tmp_path):
    """A log of exactly l rows once gave a 'simulated' log of sigma_0 alone, exit 0."""
    logs = plain_logs(tmp_path / "logs", runs=1, rows=10)
    model = paper_ckpt().save(tmp_path / "m.pt")
    out = tmp_path / "sim"
    code, err = simulate(model, logs, out)
    assert "the model's window alone: no row is left to simulate" in assert_one_line(
        code, err, "simulate", logs / "log_30_0.csv"
    )
    assert not out.exists()


def test_split_never_writes_through_a_link_into_a_log_it_read(tmp_path):
    logs = plain_logs(tmp_path / "logs")
    out = tmp_path / "split"
    out.mkdir()
    (out / "train.json").symlink_to(logs / "log_30_1.csv")
    before = (logs / "log_30_1.csv").read_bytes()
    code, err = run_cli(["split", "--logs", str(logs), "--pattern", "log_{x}_{run}.csv", "--out", str(out)])
    assert "is an input of this command" in assert_one_line(code, err, "split", out / "train.json")
    assert (logs / "log_30_1.csv").read_bytes() == before


def test_a_nan_controller_parameter_is_blamed_on_the_controller(tmp_path):
    """The preset's goals read the threshold: a NaN there was once reported as goal 'steady_count'."""
    system = description(tmp_path, params="threshold = nan", extra='[versions]\nparams = ["x"]\n')
    (tmp_path / "system.toml").write_text(
        system.read_text().replace('name = "mini"', 'name = "mini"\ngoals_preset = "lane-keeping"')
    )
    code, err = split(tmp_path / "s", str(plain_logs(tmp_path / "logs")), "--system", str(system))
    assert "[controller] params hold a non-finite number (nan)" in assert_one_line(code, err, "split", system)


def test_a_model_is_never_simulated_from_logs_of_another_period(tmp_path):
    """A 40 ms model once simulated 80 ms logs (and scored them against 80 ms real ones) silently."""
    system = description(tmp_path, period="80", extra='[versions]\nparams = ["x"]\n')
    logs = plain_logs(tmp_path / "logs", period=80, rows=30)
    model = paper_ckpt().save(tmp_path / "m.pt")  # trained at 40 ms
    code, err = simulate(model, logs, tmp_path / "sim", "--system", str(system))
    line = assert_one_line(code, err, "simulate", logs / "log_30_0.csv")
    assert "its rows are 80 ms apart (median), the model" in line and "trained at a 40 ms period" in line


def test_a_sidecar_parameter_written_as_text_is_refused(tmp_path):
    """``"x": "30"`` built the controller, but its version never matched the real x = 30."""
    logs = tmp_path / "twin"
    write_logs(generate(ControllerSpec("lane-keeping", {"x": 30}), 2, 20, seed=1), logs)
    side = sorted(logs.glob("*.meta.json"))[0]
    meta = json.loads(side.read_text())
    meta["controller"]["params"]["x"] = "30"
    side.write_text(json.dumps(meta))
    code, err = run_cli(["split", "--logs", str(logs), "--out", str(tmp_path / "s")])
    assert "controller parameter 'x' is the text '30'; write the number itself" in assert_one_line(
        code, err, "split", side
    )


def test_where_selects_a_version_by_its_number_however_written(tmp_path):
    logs = plain_logs(tmp_path / "logs")
    for written in ("30", "3e1", "30.0"):
        code, err = split(tmp_path / "s", str(logs), "--where", f"x={written}")
        assert code == 0, (written, err)
        assert len(json.loads((tmp_path / "s" / "train.json").read_text())["logs"]) == 3


def test_identical_runs_are_said_to_be_one(tmp_path):
    """A deterministic model (or --mean) writes the same run --runs times: verify would count each."""
    logs = plain_logs(tmp_path / "logs", runs=1)
    code, err = simulate(paper_ckpt().save(tmp_path / "m.pt"), logs, tmp_path / "sim", "--runs", "3")
    assert code == 0, err
    assert "the 3 runs of each initial log are one run written 3 times" in err
    code, err = simulate(paper_ckpt("gaussian").save(tmp_path / "g.pt"), logs, tmp_path / "sim2", "--runs", "3")
    assert code == 0 and "one run written" not in err, err
    sims = sorted((tmp_path / "sim2").glob("*.csv"))
    assert len(sims) == 3 and sims[0].read_text() != sims[1].read_text()  # sampled: the note would be wrong
