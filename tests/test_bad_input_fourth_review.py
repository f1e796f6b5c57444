"""Regressions of the fourth bad-input review (stop 40). Each input here once ended in a traceback,
passed silently into files envi could not read back, or gave a note before the error (two or more
lines for one mistake). Each must now be one line naming the file or option, exit code 2."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from tests.test_bad_input_audit import assert_one_line, run_cli

DESCRIPTION = """[system]
name = "mini"
period_ms = {period}
[controller]
name = "lane-keeping"
params = {{{params}}}
[[signals]]
name = "color"
role = "state"
range = [0, 100]
resolution = 1
[[signals]]
name = "angle"
role = "action"
range = [-90, 90]
{extra}"""


def description(tmp_path: Path, period: str = "40", params: str = "", extra: str = "") -> Path:
    path = tmp_path / "system.toml"
    path.write_text(DESCRIPTION.format(period=period, params=params, extra=extra))
    return path


@pytest.mark.parametrize(
    ("kind", "fields", "said"),
    [
        (
            "goal given as text",
            {"extra": '[[goals]]\nmetric = "max_abs_dev"\nsignal = "color"\nsetpoint = "40"'},
            "parameter 'setpoint' must be a finite number",
        ),
        (
            "goal given as inf",
            {"extra": '[[goals]]\nmetric = "max_abs_dev"\nsignal = "color"\nsetpoint = inf'},
            "parameter 'setpoint' must be a finite number",
        ),
        ("NaN controller gain", {"params": "threshold = nan"}, "non-finite number"),
        ("unknown controller parameter", {"params": "bogus = 1"}, "unknown parameter(s) bogus"),
        (
            "map into a parameter the controller lacks",
            {"extra": '[versions]\nmap = {x = "loops.3.kp"}'},
            "unknown parameter(s) loops",
        ),
        ("a period of 1e300 ms", {"period": "1e300"}, "'period_ms' must lie in"),
        ("training input noise of 1e300", {"extra": "[training]\ninput_noise = 1e300"}, "input_noise must be"),
    ],
)
def test_a_description_is_refused_when_read(mini, tmp_path, kind, fields, said):
    """These once passed the reader: the goal reached numpy ('ufunc subtract did not contain a loop'),
    the NaN gain a manifest nothing could read, the unknown parameter a training 9 s long."""
    system = description(tmp_path, **fields)
    code, err = run_cli(["verify", "--real", str(mini["logs"]), "--sim", str(mini["logs"]), "--system", str(system)])
    assert said in assert_one_line(code, err, "verify", system), (kind, err)


@pytest.mark.parametrize(
    ("body", "said"),
    [
        ("out = 5", "[simulate] out: takes text, not 5"),
        ('out = "s"\nseed = 2.0', "[simulate] seed:"),
    ],
)
def test_a_run_file_value_of_the_wrong_kind_is_one_line(mini, tmp_path, body, said):
    """``out = 5`` once reached ``os.fspath`` (TypeError traceback)."""
    run = tmp_path / "run.toml"
    run.write_text(f'[simulate]\nmodel = "{mini["model"]}"\ninit-logs = ["{mini["logs"]}"]\n{body}\n')
    code, err = run_cli(["simulate", "--config", str(run)])
    lines = err.splitlines()
    assert code == 2 and len(lines) == 1 and said in lines[0] and str(run) in lines[0], err


def test_envis_own_run_file_reads_back_with_a_yes_no_option(mini, tmp_path):
    """``--context`` written as ``context = true`` into ``<model>.run.toml`` was refused when read."""
    model = tmp_path / "m.pt"
    run = tmp_path / "run.toml"
    run.write_text(
        f'[train]\nlogs = ["{mini["logs"]}"]\noutput = "{model}"\nepochs = 1\nhidden = "8"\nmembers = 1\nquiet = true\n'
    )
    code, err = run_cli(["train", "--config", str(run), "--context"])
    assert code == 0, err
    written = Path(f"{model}.run.toml")
    assert "context = true" in written.read_text()
    code, err = run_cli(["train", "--config", str(written), "-o", str(tmp_path / "again.pt")])
    assert code == 0, err


@pytest.mark.parametrize(
    ("argv", "cmd", "said"),
    [
        (["train", "--hidden", "100000,100000"], "train", "weights between hidden layers"),
        (["diagnose", "--runs", "100000000"], "diagnose", "--runs 100000000: at most"),
    ],
)
def test_sizes_beyond_memory_are_refused_before_the_work(mini, tmp_path, argv, cmd, said):
    """Both once ran into a MemoryError traceback (40 GB asked for at the first training step)."""
    given = {
        "train": ["--logs", str(mini["logs"]), "-o", str(tmp_path / "m.pt")],
        "diagnose": ["--model", str(mini["model"]), "--real", str(mini["logs"]), "--out", str(tmp_path / "d")],
    }[cmd]
    code, err = run_cli([*argv, *given])
    assert said in assert_one_line(code, err, cmd, said.split(":")[0].split(" ")[0])


def test_impossible_validation_sizes_are_refused_before_any_trial(tmp_path):
    """``--steps 1`` once failed every trial and reported 'top-1 nan%', false alarms 0%."""
    base = ["diagnose", "validate", "--cases", "none", "--seeds", "1", "--out", str(tmp_path / "v")]
    code, err = run_cli([*base, "--steps", "1"])
    assert "--history" in assert_one_line(code, err, "diagnose", "--steps 1")
    code, err = run_cli([*base, "--diag", "1"])
    assert "half to choose" in assert_one_line(code, err, "diagnose", "--diag 1")
    assert not (tmp_path / "v").exists()


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["--param", "x=30", "x=40"], "x is given twice"),
        (["--param", "x=30", "--effects", "delay=2,delay=3"], "delay is given twice"),
        (["--param", "x=30", "--effects", "jitter.extra_ms=1e300"], "extra_ms"),
        (["--param", "x=30", "--effects", "lag=1e300"], "tau_ms"),
        (["--param", "x=30", "--out", ""], "--out: an empty value"),
    ],
)
def test_twin_generate_refuses_what_it_kept_silently(tmp_path, argv, said):
    """Each was accepted: the last of two values kept, a jitter whose time stamps reached 1e300 (no
    reader could take their period), a lag so slow the steering froze, an empty --out written into
    the current folder."""
    out = ["--out", str(tmp_path / "t")] if "--out" not in argv else []
    code, err = run_cli(["twin", "generate", "--runs", "1", *argv, *out])
    assert said in assert_one_line(code, err, "twin generate", said.split(" ")[0]), err
    assert not (tmp_path / "t").exists()


def gappy_logs(mini: dict[str, Path], tmp_path: Path) -> Path:
    """``mini``'s logs, one of them marked by its sidecar as missing rows inside sigma_0."""
    logs = tmp_path / "gappy"
    shutil.copytree(mini["logs"], logs)
    sidecar = sorted(logs.glob("*.meta.json"))[0]
    meta = json.loads(sidecar.read_text())
    sidecar.write_text(json.dumps({**meta, "breaks": [3]}))
    return logs


@pytest.mark.parametrize(
    ("argv", "cmd"),
    [
        (["simulate", "--controller", "nosuch"], "simulate"),
        (["simulate", "--runs", "100000000"], "simulate"),
        (["check", "--require", "bogus(color) <= 3"], "check"),
        (["check", "--unseen", "x=nan"], "check"),
    ],
)
def test_a_note_never_comes_before_the_error(mini, tmp_path, argv, cmd):
    """The note on rows missing inside sigma_0 once came first: two lines for one mistake."""
    logs = gappy_logs(mini, tmp_path)
    given = ["--init-logs", str(logs), "--out", str(tmp_path / "s")] if cmd == "simulate" else ["--real", str(logs)]
    code, err = run_cli([argv[0], "--model", str(mini["model"]), *given, *argv[1:]])
    assert_one_line(code, err, cmd, "")
    assert not (tmp_path / "s").exists()  # nor an empty folder left behind


def test_notes_still_come_when_the_command_succeeds(mini, tmp_path):
    logs = gappy_logs(mini, tmp_path)
    code, err = run_cli(
        ["simulate", "--model", str(mini["model"]), "--init-logs", str(logs), "--out", str(tmp_path / "s")]
    )
    assert code == 0 and "envi simulate: note: " in err and "rows are missing before row 3" in err, err


def test_train_option_conflicts_are_one_line_even_with_a_pause_note(mini, tmp_path):
    logs = tmp_path / "paused"
    shutil.copytree(mini["logs"], logs)
    first = sorted(logs.glob("*.csv"))[0]
    rows = first.read_text().splitlines()
    t = [float(r.split(",")[0]) for r in rows[1:]]
    shifted = [rows[0]] + [
        f"{ti + (11000 if i >= 20 else 0):g}," + r.split(",", 1)[1] for i, (ti, r) in enumerate(zip(t, rows[1:]))
    ]
    first.write_text("\n".join(shifted) + "\n")
    argv = ["train", "--logs", str(logs), "-o", str(tmp_path / "m.pt"), "--algorithm", "random"]
    code, err = run_cli([*argv, "--resume"])
    assert "--resume" in assert_one_line(code, err, "train", "--resume")
    code, err = run_cli([*argv, "--members", "1"])
    assert code == 0 and "envi train: note: " in err and "pause" in err, err


def test_skipped_logs_are_one_warning_line_each(mini, tmp_path):
    """``--skip-bad`` printed Python's two-line warning per log (the file and line of envi's code)."""
    logs = tmp_path / "some_bad"
    shutil.copytree(mini["logs"], logs)
    (logs / "broken.csv").write_text("time,color,angle\n0,40\n")
    code, err = run_cli(["split", "--logs", str(logs), "--skip-bad", "--out", str(tmp_path / "sp")])
    lines = err.splitlines()
    assert code == 0 and len(lines) == 1 and lines[0].startswith("envi split: warning: "), err
    assert "broken.csv" in lines[0]


def test_a_run_file_option_outside_its_sub_command_table_is_refused(tmp_path):
    """``[twin] out = ...`` beside ``[twin.generate]`` was ignored without a word."""
    run = tmp_path / "run.toml"
    run.write_text(f'[twin.generate]\nout = "{tmp_path / "t"}"\nparam = ["x=30"]\n[twin]\nout = "elsewhere"\n')
    code, err = run_cli(["twin", "generate", "--config", str(run)])
    lines = err.splitlines()
    assert code == 2 and len(lines) == 1 and "[twin] out:" in lines[0] and "[twin.generate]" in lines[0], err


def test_an_empty_list_of_logs_says_so(tmp_path):
    """``logs = []`` in a run file said 'error: : no logs found'."""
    run = tmp_path / "run.toml"
    run.write_text(f'[split]\nlogs = []\nout = "{tmp_path / "sp"}"\n')
    code, err = run_cli(["split", "--config", str(run)])
    assert "no logs given" in assert_one_line(code, err, "split", "no logs given")


def test_an_stl_bound_in_exponent_form_is_not_said_to_have_a_unit():
    from envi_py.goals.requirements import parse
    from envi_py.system import RequirementSpec

    with pytest.raises(ValueError, match=r"must be \[lo:hi\] with whole numbers of samples"):
        parse(RequirementSpec("R", "eventually[0:1e400] (color >= 5)", "stl", 0.9), ["color", "angle"])
    with pytest.raises(ValueError, match="has a unit"):
        parse(RequirementSpec("R", "eventually[0:5s] (color >= 5)", "stl", 0.9), ["color", "angle"])


def test_init_on_logs_with_sidecars_drafts_what_reads_them_back(mini, tmp_path):
    """The draft named the file name's field ``v1``, kept 'lane-keeping' as a guess and the data's
    narrower ranges; ``verify`` with that draft then refused the logs ('no version parameter v1')."""
    draft = tmp_path / "system.toml"
    code, err = run_cli(["init", "--logs", str(mini["logs"]), "-o", str(draft)])
    assert code == 0, err
    text = draft.read_text()
    assert 'pattern = "twin_{x}_{run}.csv"' in text and 'name = "lane-keeping"  # from the sidecars' in text
    assert "range = [-90.0, 90.0]" in text  # the sidecars' declared limits of the steering angle
    code, err = run_cli(["split", "--logs", str(mini["logs"]), "--system", str(draft), "--out", str(tmp_path / "sp")])
    assert code == 0, err


def test_an_unknown_controller_parameter_holding_a_line_break_stays_on_one_line():
    """Found by the sidecar fuzzer (Hypothesis) this stop: a parameter named '\\n' broke the line."""
    from envi_py.controllers import ControllerSpec

    with pytest.raises(ValueError) as caught:
        ControllerSpec("lane-keeping", {"\n": 1, "bogus": 2}).build()
    assert "\n" not in str(caught.value) and "'\\n', bogus" in str(caught.value)


def test_when_every_log_is_skipped_the_error_says_why(tmp_path):
    """A failed command's held warnings are not shown, so the one line names the first bad log's fault."""
    logs = tmp_path / "all_bad"
    logs.mkdir()
    (logs / "broken.csv").write_text("time,color,angle\n0,40,30\n40,abc,30\n")
    code, err = run_cli(["split", "--logs", str(logs), "--skip-bad", "--out", str(tmp_path / "sp")])
    line = assert_one_line(code, err, "split", "broken.csv")
    assert "every log was bad and skipped (1)" in line and "non-numeric" in line, line
