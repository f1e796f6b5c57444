"""The main job on the project's own data: the calibrated twin plays the field.

Twin logs of three controller versions (x = 10, 30, 50) are written like field logs; a BC model is
trained on some (TMVK), selected on others, simulated from the initial windows of held-out logs of
all five versions (x = 20 and 40 never trained on: TMVU), and verified against them.
"""

from __future__ import annotations

from pathlib import Path

from .controllers import ControllerSpec
from .logs import group_by_controller, load_logs, write_log
from .train import train
from .simulate import simulate_versions
from .verify import to_text, verify, write_report


def run_demo(out: Path, seed: int = 0, epochs: int = 300, runs_per_version: int = 30) -> Path:
    """Generate, train, simulate, verify; returns the report's Markdown path."""
    from .twin import generate, write_logs

    data = out / "data"
    for x in (10, 20, 30, 40, 50):
        write_logs(generate(ControllerSpec("lane-keeping", {"x": x}), runs_per_version, 100, seed=seed + x), data)
    logs = load_logs(data, min_length=11)
    train_logs, val_logs, test_logs = [], [], []
    for group in group_by_controller(logs).values():
        x = group[0].param["x"]
        if x in (10, 30, 50):
            train_logs += group[:15]
            val_logs += group[15:20]
        test_logs += group[20:]
    print(f"twin data: {len(logs)} logs in {data}; training on {len(train_logs)} (x=10,30,50), "
          f"validating on {len(val_logs)}, verifying on {len(test_logs)} (all five versions)")
    ckpt = train("bc", train_logs, val_logs, seed=seed, epochs=epochs, progress=True)
    ckpt.save(out / "model.pt")
    sims = simulate_versions(ckpt, test_logs, runs=10, seed=seed)
    for lg in sims:
        write_log(lg, out / "sim" / f"{lg.meta.run_id}_{lg.param.get('x', 0):g}.csv")
    results = verify(test_logs, sims, seed=seed)
    print(to_text(results))
    md, _ = write_report(results, out / "report", "Demo: BC model of the twin, TMVK (10, 30, 50) and TMVU (20, 40)")
    print(f"report: {md}")
    return md
