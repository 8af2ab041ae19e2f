"""Mutation check of the test suite's teeth (``make mutate``; not part of ``make test``).

Applies a handful of deliberate small faults, one at a time, to a *copy* of the repository
(firmware/, host/, sim/, tests/, docs/ and pyproject.toml copied into a temporary
directory; node_modules/ and build/ linked) -- never to the working tree -- and runs the
tests that should catch each one (``pytest -x -q`` on a chosen subset, with a timeout).
A fault no test catches "survived": the script prints the table and exits 1.

The subsets are behavioural tests.  The generated-file checks (tests/test_generated.py,
the bit-for-bit comparison of firmware/fastpath.py with firmware/controller.py in
tests/test_firmware_fastpath.py) would flag any edit of the controller as stale; they are
left out so that a fault counts as caught only when a test sees what it does.

Before the mutants, the union of the subsets runs once on the unmodified copy: a subset
that fails without a fault proves nothing (exit 2).

    python -m host.bench.mutate                 # every mutant
    python -m host.bench.mutate --only crc_byte_order --only cobs_feed_off_by_one
    python -m host.bench.mutate --list
    python -m host.bench.mutate --only sign_gain_kb0 --tests tests/test_firmware_fixed_vs_float.py
    python -m host.bench.mutate --json out/mutate.json

Exit status: 0 every mutant caught, 1 some survived, 2 the check itself could not run
(a mutation's text not found -- the source moved on: update MUTANTS -- or the baseline failed).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
COPY_DIRS = ("firmware", "host", "sim", "tests", "docs")
COPY_FILES = ("pyproject.toml",)
LINK_DIRS = ("node_modules", "build")  # large, read-only for the tests: linked, not copied

FW_NUMERIC = ("tests/test_firmware_fixed_vs_float.py", "tests/test_export_headroom.py")
FW_SATURATION = ("tests/test_firmware_saturation.py",)
PROTO = ("tests/test_proto_framing.py", "tests/test_proto_mpy.py", "tests/test_firmware_link.py")
ALLOC = ("tests/test_firmware_alloc.py", "tests/test_firmware_paced_loop.py")


@dataclass(frozen=True)
class Mutant:
    """One fault: replace ``old`` by ``new`` (exactly ``count`` occurrences) in ``path``."""

    name: str
    what: str
    path: str
    old: str
    new: str
    tests: tuple[str, ...]
    count: int = 1


MUTANTS: tuple[Mutant, ...] = (
    Mutant("shift_force_off_by_one", "controller: force accumulator shifted by SK + 1 (half the force)",
           "firmware/controller.py", "u = acc >> self.sk\n", "u = acc >> (self.sk + 1)\n", FW_NUMERIC),
    Mutant("shift_update_off_by_one", "controller: tilt-rate update row shifted by SA[3] - 1",
           "firmware/controller.py", "q = a >> sa[3]\n", "q = a >> (sa[3] - 1)\n", FW_NUMERIC),
    Mutant("shift_duty_off_by_one", "motor: force -> duty shifted by SD - 1 (twice the duty)",
           "firmware/motor.py", "d = acc >> self.sd\n", "d = acc >> (self.sd - 1)\n",
           FW_SATURATION + FW_NUMERIC),
    Mutant("sign_gain_kf1", "controller: sign of the cart-speed feedback gain KF[1] flipped",
           "firmware/controller.py", "acc = kf[0] * x0 + kf[1] * x1 +", "acc = kf[0] * x0 - kf[1] * x1 +",
           FW_NUMERIC),
    Mutant("sign_gain_kb0", "gain table: sign of the first stored-force gain KB[0] flipped",
           "host/design/export.py", "[-kb[i] for i in range(d)]", "[(kb[i] if i == 0 else -kb[i]) for i in range(d)]",
           ("tests/test_export_headroom.py", "tests/test_firmware_fixed_vs_float.py")),
    Mutant("force_saturation_removed", "controller: the force clamp to +-ULIM removed (sat flag kept)",
           "firmware/controller.py", "            u = l\n            sat = 1\n",
           "            sat = 1\n", FW_SATURATION + FW_NUMERIC),
    Mutant("duty_saturation_removed", "motor: the duty clamp to +-max_duty removed",
           "firmware/motor.py", "        if d > l:\n            return l\n        if d < -l:\n            return -l\n",
           "", FW_SATURATION + FW_NUMERIC),
    Mutant("crc_byte_order", "framing: the encoder writes the CRC little-endian",
           "firmware/framing.py", "        raw[2 + n] = crc >> 8\n        raw[3 + n] = crc & 0xFF\n",
           "        raw[2 + n] = crc & 0xFF\n        raw[3 + n] = crc >> 8\n", PROTO),
    Mutant("cobs_feed_off_by_one", "framing: Decoder.feed counts a COBS block one byte long",
           "firmware/framing.py", "            self._left = b - 1\n", "            self._left = b\n", PROTO),
    Mutant("cobs_scan_off_by_one", "framing: Decoder.scan counts a COBS block one byte short",
           "firmware/framing.py", "                left = b - 1\n", "                left = b - 2\n", PROTO),
    Mutant("alloc_in_loop", "app: a list allocated in every loop iteration",
           "firmware/app.py", "        self.duty = duty\n", "        self.duty = duty\n        self._last = [duty]\n",
           ALLOC),
)


def make_copy(dest: Path) -> Path:
    """Copy the parts of the working tree the tests need into ``dest`` (a new directory)."""
    ign = shutil.ignore_patterns("__pycache__", "*.pyc", ".pytest_cache", ".hypothesis")
    for d in COPY_DIRS:
        shutil.copytree(ROOT / d, dest / d, ignore=ign)
    for f in COPY_FILES:
        shutil.copy2(ROOT / f, dest / f)
    for d in LINK_DIRS:
        if (ROOT / d).exists():
            (dest / d).symlink_to(ROOT / d)
    return dest


def _env(copy: Path) -> dict[str, str]:
    env = dict(os.environ)
    # the venv has the project installed editable (pointing at the working tree): put the
    # copy first so that every import, also in subprocesses, resolves to the mutated files
    env["PYTHONPATH"] = str(copy) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    return env


def check_imports_from_copy(copy: Path) -> None:
    """Fail loudly if the copy's packages are shadowed by the working tree's."""
    code = "import firmware, host, sim; print(firmware.__file__); print(host.__file__); print(sim.__file__)"
    out = subprocess.run([sys.executable, "-c", code], cwd=copy, env=_env(copy), capture_output=True, text=True,
                         check=True).stdout.split()
    bad = [p for p in out if not Path(p).resolve().is_relative_to(copy.resolve())]
    if bad:
        raise SystemExit(f"mutate: imports resolve outside the copy: {bad}")


def run_tests(copy: Path, tests: tuple[str, ...], timeout: float) -> tuple[str, str, float]:
    """Run ``pytest -x -q`` on ``tests`` in the copy: (outcome, first failing test, seconds).

    outcome: "passed" (rc 0), "failed" (rc 1), "timeout", or "error" (collection/usage errors).
    """
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", "-m", "not rp2040", *tests]
    t0 = time.monotonic()
    try:
        r = subprocess.run(cmd, cwd=copy, env=_env(copy), capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return "timeout", f"(no result in {timeout:g} s)", time.monotonic() - t0
    dt = time.monotonic() - t0
    first = ""
    for line in r.stdout.splitlines():
        m = re.match(r"^(FAILED|ERROR) (\S+)", line)
        if m:
            first = m.group(2)
            break
    if r.returncode == 0:
        return "passed", "", dt
    if r.returncode == 1:
        return "failed", first, dt
    return "error", first or (r.stdout + r.stderr)[-400:], dt


def apply(copy: Path, m: Mutant) -> str:
    """Apply ``m`` to the copy; returns the original text (to restore)."""
    f = copy / m.path
    text = f.read_text()
    n = text.count(m.old)
    if n != m.count:
        raise LookupError(f"{m.name}: {m.old!r} occurs {n} times in {m.path}, expected {m.count}")
    f.write_text(text.replace(m.old, m.new))
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m host.bench.mutate", description=__doc__.splitlines()[0])
    ap.add_argument("--only", action="append", default=[], help="run this mutant (repeatable)")
    ap.add_argument("--list", action="store_true", help="list the mutants and their tests, run nothing")
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds per pytest run (default 600)")
    ap.add_argument("--tests", nargs="+", help="run these tests for every chosen mutant instead of its own subset")
    ap.add_argument("--no-baseline", action="store_true", help="skip the run of the subsets without a fault")
    ap.add_argument("--keep", action="store_true", help="keep the temporary copy (its path is printed)")
    ap.add_argument("--json", help="also write the results to this file")
    a = ap.parse_args(argv)

    chosen = [m for m in MUTANTS if not a.only or m.name in a.only]
    if a.tests:
        from dataclasses import replace

        chosen = [replace(m, tests=tuple(a.tests)) for m in chosen]
    unknown = set(a.only) - {m.name for m in MUTANTS}
    if unknown:
        print(f"mutate: unknown mutant(s) {sorted(unknown)}; --list shows them", file=sys.stderr)
        return 2
    if a.list:
        for m in MUTANTS:
            print(f"{m.name:<26} {m.path:<24} {m.what}\n{'':<26} tests: {' '.join(m.tests)}")
        return 0

    tmp = Path(tempfile.mkdtemp(prefix="upright-mutate-"))
    copy = make_copy(tmp / "repo")
    try:
        check_imports_from_copy(copy)
        print(f"mutate: copy of the working tree in {copy}", flush=True)
        if not a.no_baseline:
            union = tuple(dict.fromkeys(t for m in chosen for t in m.tests))
            outcome, first, dt = run_tests(copy, union, a.timeout)
            print(f"mutate: baseline (no fault) {outcome} in {dt:.0f} s: {' '.join(union)}", flush=True)
            if outcome != "passed":
                print(f"mutate: the subsets fail without a fault ({first}); fix that first", file=sys.stderr)
                return 2
        rows = []
        for m in chosen:
            try:
                original = apply(copy, m)
            except LookupError as e:
                print(f"mutate: {e}", file=sys.stderr)
                rows.append(dict(mutant=m.name, what=m.what, outcome="not applied", caught_by="", seconds=0.0))
                continue
            try:
                outcome, first, dt = run_tests(copy, m.tests, a.timeout)
            finally:
                (copy / m.path).write_text(original)
            caught = outcome in ("failed", "timeout")
            rows.append(dict(mutant=m.name, what=m.what, outcome="caught" if caught else outcome,
                             caught_by=first if caught else "", seconds=round(dt, 1)))
            print(f"  {m.name:<26} {rows[-1]['outcome']:<8} {dt:6.1f} s  {first if caught else ''}", flush=True)
    finally:
        if a.keep:
            print(f"mutate: kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)

    print()
    print(f"{'mutant':<26} {'outcome':<11} {'seconds':>7}  caught by")
    for r in rows:
        print(f"{r['mutant']:<26} {r['outcome']:<11} {r['seconds']:>7.1f}  {r['caught_by']}")
    survived = [r["mutant"] for r in rows if r["outcome"] == "passed"]
    broken = [r["mutant"] for r in rows if r["outcome"] in ("error", "not applied")]
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps(dict(rows=rows, survived=survived, broken=broken), indent=2))
    if survived:
        print(f"\nmutate: SURVIVED (no test caught them): {', '.join(survived)}")
        return 1
    if broken:
        print(f"\nmutate: could not judge: {', '.join(broken)}")
        return 2
    print(f"\nmutate: all {len(rows)} mutants caught")
    return 0


if __name__ == "__main__":
    sys.exit(main())
