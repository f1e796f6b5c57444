"""The README's "From a notebook" section runs as written (in a fresh folder, plots off screen)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def notebook_block() -> str:
    text = (ROOT / "README.md").read_text()
    section = text.split("## From a notebook", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 1, "the section holds one Python block"
    return blocks[0]


def test_the_notebook_section_runs_and_says_what_it_promises(tmp_path):
    code = notebook_block()
    assert "from envi_py import api as envi" in code
    env = {**os.environ, "MPLBACKEND": "Agg"}
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-2000:]
    out = done.stdout
    # the verification table names every goal of the car, the verdicts every version, the diagnosis speaks
    for goal in ("lane deviation", "closest approach", "gap error"):
        assert goal in out
    assert "kp_steer=0.8,kp_speed=18" in out and "kp_steer=2,kp_speed=18" in out
    assert "The largest closed-loop gap" in out or "Every goal" in out
    assert (tmp_path / "work" / "nb").is_dir()
