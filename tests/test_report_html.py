"""The HTML reports in a real headless browser: each page loads without console errors or network
requests, every figure decodes, the verdict table is the page's first table and provenance is there.

The browser is the system's Chromium (``apt-get install chromium``; ``./dev.sh setup`` does it) driven
by playwright; no browser is ever downloaded. Outside CI a machine without Chromium skips with the
reason; under ``CI=true`` a missing browser fails.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

import pytest

from envi_py.check import check, write_check
from envi_py.controllers import ControllerSpec
from envi_py.logs import load_logs
from envi_py.simulate import simulate_versions
from envi_py.system import RequirementSpec, load_system
from envi_py.train import train
from envi_py.twin import generate, write_logs
from envi_py.verify import verify, write_report

ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


DEBIAN_CHROMIUM = Path("/usr/bin/chromium")


def _chromium() -> str:
    path = shutil.which("chromium") or (str(DEBIAN_CHROMIUM) if DEBIAN_CHROMIUM.exists() else None)
    why = None
    if path is None:
        why = "no Chromium: apt-get install chromium (./dev.sh setup installs it)"
    else:
        try:
            import playwright.sync_api  # noqa: F401
        except ImportError:
            why = "no playwright: pip install -e '.[test]'"
    if why is not None:
        if os.environ.get("CI") == "true":
            pytest.fail(f"CI must run the browser test: {why}")
        pytest.skip(why)
    return str(path)


@pytest.fixture(scope="module")
def browser() -> Any:
    exe = _chromium()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=exe, args=ARGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def pages(tmp_path_factory) -> dict[str, Path]:
    """verify's and check's pages on a small lane-keeping twin: 2 versions, a few seconds of training."""
    d = tmp_path_factory.mktemp("logs")
    for x in (10, 30):
        write_logs(generate(ControllerSpec("lane-keeping", {"x": x}), 8, 50, seed=x), d)
    logs = load_logs(d)
    fit = [lg for i, lg in enumerate(logs) if i % 8 < 4]
    real = [lg for i, lg in enumerate(logs) if i % 8 >= 4]
    ckpt = train("bc", fit, [], epochs=5, hidden=(16, 16), history=10, seed=0)
    out = tmp_path_factory.mktemp("reports")
    model = ckpt.save(out / "m.pt")
    system = load_system("lane-keeping")
    sims = simulate_versions(ckpt, real, runs=3, seed=0, engine="torch")
    results = verify(real, sims, system)
    write_report(results, out / "verify", real=real, sim=sims, system=system)
    rows = check(
        ckpt,
        real,
        [RequirementSpec("near", "max_abs_dev(color, 40) <= 35", "metric", 0.9)],
        max_runs=100,
        batch=50,
        sims_per_start=3,
        engine="torch",
    )
    meta = {"model": str(model), "alpha": 0.05, "delta": 0.05, "max_runs": 100, "batch": 50, "sims_per_start": 3}
    write_check(rows, out / "check", meta)
    return {"verify": out / "verify" / "report.html", "check": out / "check" / "check.html"}


def _inspect(browser: Any, page_file: Path) -> dict[str, Any]:
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    errors: list[str] = []
    requests: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("request", lambda r: requests.append(r.url) if not r.url.startswith(("file:", "data:")) else None)
    page.goto(page_file.as_uri(), wait_until="load")
    found = page.evaluate(
        """() => {
        const imgs = [...document.images];
        const first = document.querySelector('table');
        return {
          images: imgs.length,
          broken: imgs.filter(i => !(i.complete && i.naturalWidth > 0)).map(i => i.alt),
          firstTableIsVerdict: !!first && first.classList.contains('verdict') && !!first.closest('#verdict'),
          firstHeader: first ? first.querySelector('th').textContent : null,
          provenance: (document.querySelector('#provenance') || {}).textContent || '',
          lastSection: [...document.querySelectorAll('body > section')].pop().id,
          scripts: document.scripts.length,
        };
    }"""
    )
    page.close()
    return {**found, "errors": errors, "requests": requests}


@pytest.mark.parametrize("which", ["verify", "check"])
def test_report_page_renders_in_a_real_browser(browser, pages, which) -> None:
    got = _inspect(browser, pages[which])
    assert got["errors"] == [] and got["requests"] == []  # self-contained: no network, no console error
    assert got["images"] >= 1 and got["broken"] == []
    assert got["firstTableIsVerdict"] and got["firstHeader"] == "version"
    assert got["lastSection"] == "provenance" and "envi version" in got["provenance"]
    assert got["scripts"] == 0
    if which == "check":
        assert "model sha256" in got["provenance"] and len(got["provenance"]) > 64


def test_verify_page_shows_traces_with_fit_and_every_versions_distributions(pages) -> None:
    text = pages["verify"].read_text()
    assert text.count('<img src="data:image/png;base64,') == 3  # x=10 traces, x=30 traces, distributions
    assert "median fit %" in text and "acc floor" in text
    md = (pages["verify"].parent / "report.md").read_text()
    assert md.startswith("# Verification report\n\n| version |") and "## Provenance" in md
    for name in ("traces_x=10", "traces_x=30", "metric_distributions"):
        assert (pages["verify"].parent / "report_figures" / f"{name}.png").stat().st_size > 1000


def test_a_missing_browser_skips_only_outside_ci(monkeypatch, tmp_path) -> None:
    import sys

    monkeypatch.setattr(shutil, "which", lambda *_: None)
    monkeypatch.setattr(sys.modules[__name__], "DEBIAN_CHROMIUM", tmp_path / "no-chromium")
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="CI must run the browser test: no Chromium"):
        _chromium()
    monkeypatch.delenv("CI")
    with pytest.raises(pytest.skip.Exception, match="apt-get install chromium"):
        _chromium()
