"""A seed ensemble (``envi train --members K``): one checkpoint of K models, each simulated run drawn
by one member, in both engines, saved and loaded with every member's weights under its hash."""

from __future__ import annotations

import json
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from envi_py import native
from envi_py.cli import main
from envi_py.export_cli import main as export_main
from envi_py.export import export, read_metadata
from envi_py.logs import load_logs, read_log, write_log
from envi_py.metrics import driving_metrics
from envi_py.model import Checkpoint
from envi_py.simulate import ensemble_rollout, iter_simulate, members_of_runs, rollout, simulate_logs
from envi_py.system import lane_keeping, load_system, shipped
from envi_py.train import train
from envi_py.twin import TwinProfile, generate
from firmware_bridge.host.inject import CheckpointModel

from .conftest import make_log
from .test_export import paper_ckpt
from .test_native import LANE, envi_sim, windows


@pytest.fixture(scope="module")
def lane_logs():
    logs = generate(LANE, 6, 40, {"noise": 2.0}, seed=0, profile=TwinProfile())
    return logs[:4], logs[4:]


def three() -> Checkpoint:
    """Three deterministic members that answer differently (seeded weights 0, 1, 2)."""
    return Checkpoint.ensemble([paper_ckpt("deterministic", seed=s) for s in range(3)])


@pytest.mark.parametrize("members, batch", [(3, 10), (3, 3), (2, 7), (5, 2)])
def test_runs_are_shared_out_evenly_in_a_seeded_order(members, batch):
    pick = members_of_runs(members, batch, seed=4)
    counts = np.bincount(pick, minlength=members)
    assert counts.max() - counts.min() <= 1 and counts.sum() == batch
    assert np.array_equal(pick, members_of_runs(members, batch, seed=4))
    assert any(not np.array_equal(pick, members_of_runs(members, batch, seed=s)) for s in range(5, 10))


def test_each_run_is_its_members_own_rollout():
    """A deterministic member's run does not depend on the seed: each ensemble run must equal the
    rollout of the member the draw picked, from the run's own window, and all three must be used."""
    ens, init = three(), windows(4)
    got = rollout(ens, LANE, init, 40, runs=3, seed=11)
    pick = members_of_runs(3, len(init) * 3, 11)
    alone = [rollout(ens.member(m), LANE, init, 40, runs=3) for m in range(3)]
    for run, m in enumerate(pick):  # float32 sums differ in the last bits between batch sizes
        np.testing.assert_allclose(got[run], alone[m][run], atol=1e-4, rtol=0)
    assert len(set(pick)) == 3
    assert not np.allclose(alone[0], alone[1])  # the members differ, so the test could fail


def test_the_native_engine_shares_runs_out_as_pytorch_does():
    ens, init = three(), windows(3)
    want = rollout(ens, LANE, init, 60, runs=2, seed=5)
    rolls = [lambda i, n, r, s, c=native.load(ens.member(m)): native.rollout(c, LANE, i, n, r, s) for m in range(3)]
    np.testing.assert_allclose(ensemble_rollout(rolls, init, 60, 2, 5), want, atol=1e-4, rtol=0)
    logs = [make_log(w[:, 0], run=f"w{k}") for k, w in enumerate(init)]
    want = rollout(ens, LANE, init, 60, runs=2, seed=5 + 7919 * 60)  # the seed iter_simulate gives 60 steps
    for engine in ("native", "torch"):
        runs = [lg.values for _, _, lg in iter_simulate(ens, LANE, logs, 60, runs=2, seed=5, engine=engine)]
        assert all(lg.meta.provenance["members"] == 3 for _, _, lg in iter_simulate(ens, LANE, logs[:1], 5))
        np.testing.assert_allclose(np.stack(runs)[:, 10:], want[:, 10:], atol=1e-4, rtol=0)


def test_a_stochastic_ensemble_repeats_and_no_member_steps_in_the_ensembles_name():
    ens = Checkpoint.ensemble([paper_ckpt("gaussian", seed=s) for s in range(2)])
    init = windows(2)
    np.testing.assert_array_equal(rollout(ens, LANE, init, 30, 4, seed=3), rollout(ens, LANE, init, 30, 4, seed=3))
    with pytest.raises(ValueError, match="one member at a time"):
        ens.next_state(torch.zeros(1, ens.config.in_features))


def test_saved_and_loaded_with_every_member_under_the_hash(tmp_path):
    ens = three()
    path = ens.save(tmp_path / "e.pt")
    back = Checkpoint.load(path)
    assert back.size == 3 and back.record.hyper["members"] == 3
    for a, b in zip(ens.members, back.members):
        for k, v in a.state_dict().items():
            assert torch.equal(v, b.state_dict()[k])
    blob = torch.load(path, weights_only=True)
    blob["members"][1]["state_dict"]["mean.bias"] += 1e-3  # member 2's weights changed after saving
    torch.save(blob, tmp_path / "changed.pt")
    with pytest.raises(ValueError, match="does not match its hash"):
        Checkpoint.load(tmp_path / "changed.pt")
    single = paper_ckpt().save(tmp_path / "one.pt")
    assert Checkpoint.load(single).size == 1 and not Checkpoint.load(single).members


def test_members_must_read_and_say_the_same():
    base = paper_ckpt(seed=1)
    other = replace(base, norm=replace(base.norm, low=base.norm.low - 1.0))  # trained on other logs
    with pytest.raises(ValueError, match="member 1 reads or says other things"):
        Checkpoint.ensemble([paper_ckpt(seed=0), other])
    with pytest.raises(ValueError, match="member 0 is itself an ensemble"):
        Checkpoint.ensemble([three(), paper_ckpt()])
    with pytest.raises(ValueError, match="numbered 0..2"):
        three().member(3)


def test_training_makes_members_from_consecutive_seeds(lane_logs):
    fit, val = lane_logs
    ens = train("bc", fit, val, seed=7, epochs=2, hidden=(8,), members=2, progress=False)
    assert ens.size == 2 and [m["seed"] for m in ens.record.selection["members"]] == [7, 8]
    second = ens.member(1)  # says what it is: its own seed and selection, not the ensemble's
    assert second.record.seed == 8 and "members" not in second.record.hyper
    assert second.record.selection["best_epoch"] == ens.record.selection["members"][1]["best_epoch"]
    alone = train("bc", fit, val, seed=8, epochs=2, hidden=(8,), progress=False)
    for k, v in alone.model.state_dict().items():
        torch.testing.assert_close(ens.members[1].state_dict()[k], v)
    with pytest.raises(ValueError, match="random baseline"):
        train("random", fit, val, members=2)


def test_members_trained_at_once_in_worker_processes(lane_logs, capsys):
    """Two members in two spawned workers: the same seeds and selection as one after another (their
    weights differ in the last bits: one torch thread each), and progress says which finished."""
    fit, val = lane_logs
    both = train("bc", fit, val, seed=3, epochs=2, hidden=(8,), members=2, jobs=2, progress=True)
    assert "training 2 members (seeds 3..4), 2 at a time" in capsys.readouterr().err
    alone = train("bc", fit, val, seed=3, epochs=2, hidden=(8,), members=2, progress=False)
    assert [m["seed"] for m in both.record.selection["members"]] == [3, 4]
    for a, b in zip(both.members, alone.members):
        for k, v in a.state_dict().items():
            torch.testing.assert_close(v, b.state_dict()[k], atol=1e-4, rtol=1e-4)


def test_the_description_recommends_members_for_behaviour_cloning_only():
    lane = load_system("lane-keeping").training
    assert lane.members == 3 and lane.for_algorithm("bc")["members"] == 3
    assert "members" not in lane.for_algorithm("bcxgail") and "members" not in lane.for_algorithm("random")
    assert load_system("car").training.members == 1


def test_the_description_sets_members_and_the_command_line_wins(lane_logs, tmp_path, capsys):
    fit, val = lane_logs
    text = shipped()["lane-keeping"].read_text()
    desc = tmp_path / "lk.toml"
    assert "\nmembers = 3\n" in text
    desc.write_text(text.replace("\nmembers = 3\n", "\nmembers = 2\n"))
    for k, lg in enumerate(fit):
        write_log(lg, tmp_path / "fit" / f"f{k}.csv")
    base = ["train", "--logs", str(tmp_path / "fit"), "--system", str(desc), "--epochs", "2", "--hidden", "8"]
    assert main([*base, "--quiet", "-o", str(tmp_path / "d.pt")]) == 0
    assert "2 members (seeds 0..1)" in capsys.readouterr().out
    assert Checkpoint.load(tmp_path / "d.pt").size == 2
    assert main([*base, "--quiet", "--members", "1", "-o", str(tmp_path / "s.pt")]) == 0
    assert Checkpoint.load(tmp_path / "s.pt").size == 1
    assert main([*base, "--members", "0", "-o", str(tmp_path / "z.pt")]) == 2
    assert "--members must be at least 1" in capsys.readouterr().err
    desc.write_text(text.replace("\nmembers = 3\n", "\nmembers = 0\n"))
    assert main([*base, "-o", str(tmp_path / "z.pt")]) == 2
    assert "members must be a whole number in 1..32" in capsys.readouterr().err


def test_export_takes_one_member_and_names_the_choice(tmp_path, capsys):
    path = three().save(tmp_path / "e.pt")
    assert export_main([str(path), "-o", str(tmp_path / "e.onnx")]) == 2
    err = capsys.readouterr().err
    assert "seed ensemble of 3 members" in err and "--member 0..2" in err and not (tmp_path / "e.onnx").exists()
    assert export_main([str(path), "--member", "2", "-o", str(tmp_path / "m2.onnx")]) == 0
    want = rollout(three().member(2), LANE, windows(2), 20)
    np.testing.assert_allclose(native.rollout(tmp_path / "m2.onnx", LANE, windows(2), 20), want, atol=1e-4)
    assert export_main([str(path), "--member", "3", "-o", str(tmp_path / "m3.onnx")]) == 2
    assert "numbered 0..2" in capsys.readouterr().err


def test_hardware_in_the_loop_runs_take_the_members_in_turn():
    ens = three()
    hil = CheckpointModel(ens)
    window = windows(1)[0]
    seen = []
    for _ in range(3):
        hil.reset()
        seen.append(hil(window))
    want = [float(rollout(ens.member(m), LANE, window[None], 1)[0, -1, 0]) for m in (1, 2, 0)]
    np.testing.assert_allclose(seen, want, atol=1e-6)


def test_the_member_draw_is_the_same_in_python_and_cpp():
    twin = native._native().members_of_runs
    for members, batch, seed in [(3, 10, 5), (2, 7, 123456789012), (5, 1000, 2**63 + 5), (4, 1, 0)]:
        assert twin(members, batch, seed) == members_of_runs(members, batch, seed).tolist()


@pytest.mark.skipif(envi_sim() is None, reason="envi_sim binary not built")
def test_envi_sim_runs_an_ensemble_from_its_members_files_as_python_does(tmp_path, real_dir):
    """Each member exported alone and given to envi_sim together: every run equals the Python
    engine's run of the same ensemble (the same member per run, deterministic members), with the
    metrics in window order and ``members`` in the provenance."""
    ens = three()
    files = [export(ens.member(m), tmp_path / f"m{m}.onnx") for m in range(3)]
    init = [real_dir / f"log_30_{i}.csv" for i in range(4)]
    cmd = [envi_sim(), "--model", *map(str, files), "--init", *map(str, init), "--controller", "lane-keeping"]
    cmd += ["--param", "x=30", "--steps", "40", "--runs", "3", "--seed", "9", "--threads", "2"]
    subprocess.run([*cmd, "--out", str(tmp_path / "sim"), "--metrics", str(tmp_path / "m.json")], check=True)
    real = load_logs(init, lane_keeping().with_pattern("log_{x}_{run}.csv"))
    want = simulate_logs(ens, LANE, real, steps=40, runs=3, seed=9, engine="torch")
    got = [
        read_log(
            tmp_path / "sim" / f"{Path(lg.meta.provenance['init_log']).stem}-sim{lg.meta.provenance['replicate']}.csv"
        )
        for lg in want
    ]
    for g, w in zip(got, want):
        np.testing.assert_allclose(g.values, w.values, atol=1e-4, rtol=0)
        assert g.meta.provenance["members"] == 3
    per_run = json.loads((tmp_path / "m.json").read_text())["per_run"]
    np.testing.assert_allclose(per_run, driving_metrics(np.stack([g.states[:, 0] for g in got])), atol=1e-9)
    assert len({tuple(np.round(g.states[:, 0], 3)) for g in got[:3]}) > 1  # members differ within a window


@pytest.mark.skipif(envi_sim() is None, reason="envi_sim binary not built")
def test_envi_sim_refuses_models_of_different_ensembles_in_one_line(tmp_path, real_dir):
    base = paper_ckpt(seed=1)
    other = replace(base, norm=replace(base.norm, high=base.norm.high + 5.0))
    files = [export(paper_ckpt(seed=0), tmp_path / "a.onnx"), export(other, tmp_path / "b.onnx")]
    cmd = [envi_sim(), "--model", *map(str, files), "--init", str(real_dir / "log_30_0.csv"), "--metrics", "-"]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and not done.stdout
    assert "b.onnx: its envi.normaliser differs from" in done.stderr and "one seed ensemble" in done.stderr


@pytest.mark.skipif(envi_sim() is None, reason="envi_sim binary not built")
def test_envi_sim_says_when_it_is_given_some_members_only_and_refuses_one_twice(tmp_path, real_dir):
    """An exported member records which of how many it is: envi_sim given members 0 and 2 of 3 runs
    them as an ensemble of two and says so on stderr; member 0 given twice is one line, exit 2."""
    ens = three()
    files = [export(ens.member(m), tmp_path / f"m{m}.onnx") for m in range(3)]
    assert read_metadata(files[2])["envi.hyper"]["member"] == {"index": 2, "of": 3}
    base = [envi_sim(), "--init", str(real_dir / "log_30_0.csv"), "--controller", "lane-keeping", "--param", "x=30"]
    base += ["--steps", "20", "--metrics", "-"]

    def run(*models: Path) -> subprocess.CompletedProcess:
        return subprocess.run([*base, "--model", *map(str, models)], capture_output=True, text=True, check=False)

    some = run(files[0], files[2])
    assert some.returncode == 0 and json.loads(some.stdout)["per_run"]
    assert "note: --model gives members 0, 2 of a seed ensemble of 3; the runs are drawn by these 2 only" in some.stderr
    assert "note" not in run(*files).stderr
    twice = run(files[0], files[1], files[0])
    assert twice.returncode == 2 and twice.stderr.count("\n") == 1
    assert "m0.onnx: member 0 of the seed ensemble, as" in twice.stderr and "give each member once" in twice.stderr
