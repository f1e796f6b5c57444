"""The notebook API writes the same report as the command line: Verification.write gives report.html."""

from __future__ import annotations

import dataclasses
import json
import re

from envi_py import api as envi
from envi_py.controllers import ControllerSpec
from envi_py.twin import generate


def _as_sim(log, init):
    """A twin log standing in for a simulated run started from ``init``'s initial window."""
    meta = dataclasses.replace(log.meta, source="sim", provenance={"init_log": init.name})
    return dataclasses.replace(log, meta=meta)


def test_verification_write_gives_the_page_with_traces_fit_and_distributions(tmp_path) -> None:
    real, sim = [], []
    for x in (10, 30):
        logs = generate(ControllerSpec("lane-keeping", {"x": x}), 8, 40, seed=x)
        for i, lg in enumerate(logs):
            lg = dataclasses.replace(lg, meta=dataclasses.replace(lg.meta, run_id=f"r{x}_{i}"))
            (real if i < 4 else sim).append(lg)
    # x=10's "simulated" runs are copies of its real logs (a perfect model: fit 100 %); x=30's are other runs
    sim = [_as_sim(r, r) for r in real[:4]] + [_as_sim(s, real[4 + i]) for i, s in enumerate(sim[4:])]
    result = envi.verify(real, sim)
    page = result.write(tmp_path / "v", real, sim)
    assert page == tmp_path / "v" / "report.html"
    html = page.read_text()
    assert html.count("data:image/png;base64,") == 3  # one trace figure per version, one distribution figure
    fit_rows = re.findall(r"<tr><td>(x=\d+)</td><td>color</td>((?:<td class=num>[^<]*</td>){5})</tr>", html)
    cells = {v: re.findall(r">([^<]*)</td>", rest) for v, rest in fit_rows}
    assert cells["x=10"] == ["4", "1", "100.0", "100.0", "100.0"]  # 4 real logs, 1 run each, all identical
    assert cells["x=30"][:2] == ["4", "1"] and float(cells["x=30"][2]) < 100
    js = json.loads((tmp_path / "v" / "report.json").read_text())
    assert [g["version"] for g in js["groups"]] == ["x=10", "x=30"] and js["provenance"]["envi"]
