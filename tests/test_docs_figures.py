"""Numbers the README and the docs quote about the firmware are the firmware's own.

A figure in prose that no test ties to the code drifts (issue 25: the stall threshold was quoted as
2000 in one place and 800 in the code).  Each check reads the sentence from the document and the
constant from the module.
"""

from __future__ import annotations

import re
from pathlib import Path

from firmware import appconfig

ROOT = Path(__file__).resolve().parent.parent


def _text(name: str) -> str:
    return " ".join((ROOT / name).read_text().split())


def test_the_stall_thresholds_quoted_are_the_firmwares() -> None:
    readme = _text("README.md")
    m = re.search(r"a duty of at least (\d+) counts \(about [\d.]+ N at rest\) moves nothing for (\d+) ms", readme)
    assert m, "README no longer states the stall thresholds"
    assert (int(m.group(1)), int(m.group(2))) == (appconfig.STALL_DUTY, appconfig.STALL_MS)
    fw = _text("docs/firmware.md")
    m = re.search(r"`stall_ms` \(default (\d+);.*?`stall_duty` \(default (\d+)\)", fw)
    assert m, "docs/firmware.md no longer gives the config defaults"
    assert (int(m.group(1)), int(m.group(2))) == (appconfig.STALL_MS, appconfig.STALL_DUTY)
    for doc in ("docs/firmware.md", "docs/reliability.md"):
        for n in re.findall(r"`stall_duty` \(default (\d+)", _text(doc)) + re.findall(r"`stall_duty` \((\d+),", _text(doc)):
            assert int(n) == appconfig.STALL_DUTY, (doc, n)


def test_the_default_design_quoted_is_the_shipped_one() -> None:
    from host.design import discrete as d
    from sim.params import load_params

    doc = _text("docs/parameters.md")
    m = re.search(r"accelerates the cart at \*\*([\d.]+) m/s² from upright\*\*: `u_max = ([\d.]+) / B\[1\] = ([\d.]+) N`", doc)
    assert m, "docs/parameters.md no longer states the default clamp"
    assert float(m.group(1)) == float(m.group(2)) == d.A_CMD_DEFAULT
    assert abs(float(m.group(3)) - d.force_clamp(load_params())) < 5e-4
    m = re.search(r"\*\*LQR weights `Q = diag\(([^)]*)\)`, `R = ([\d.]+)`\*\*", doc)
    assert m, "docs/parameters.md no longer states the default weights"
    assert tuple(float(v) for v in m.group(1).split(",")) == tuple(d.Q_DEFAULT)
    assert float(m.group(2)) == d.R_DEFAULT
    m = re.search(r"`OBSERVER_DEFAULT = ([\d.]+)`", doc)
    assert m and float(m.group(1)) == d.OBSERVER_DEFAULT


def test_every_stall_duty_in_prose_is_the_firmwares() -> None:
    # the fault tables and the no-motion paragraph quote the duty as a bare number too
    fw = _text("docs/firmware.md")
    m = re.search(r"\*\*No-motion check \(F_STALL\), on by default\.\*\* (\d+) duty .*? held for (\d+) ms", fw)
    assert m, "docs/firmware.md no longer explains the no-motion check"
    assert (int(m.group(1)), int(m.group(2))) == (appconfig.STALL_DUTY, appconfig.STALL_MS)
    rel = _text("docs/reliability.md")
    m = re.search(r"`stall_duty` \((\d+), ~2 N at rest\) for `stall_ms` \((\d+) ms\)", rel)
    assert m, "docs/reliability.md no longer gives the stall thresholds"
    assert (int(m.group(1)), int(m.group(2))) == (appconfig.STALL_DUTY, appconfig.STALL_MS)
    header = (ROOT / "firmware" / "appconfig.py").read_text().split("\nSTALL_MS", 1)[0]
    # the header names the constants instead of restating them (it once said 2000)
    assert "STALL_DUTY" in header and not re.search(r"\|duty\| >= \d", header)


def test_every_default_clamp_in_prose_is_the_shipped_one() -> None:
    from host.design import catch, discrete as d

    quotes = {
        "README.md": re.findall(r"clamps the force at ([\d.]+) m/s² of cart acceleration", _text("README.md")),
        "docs/firmware.md": re.findall(r"force clamped at [\d.]+ N \(([\d.]+) m/s² of cart acceleration",
                                       _text("docs/firmware.md")),
        "host/design/catch.py": re.findall(r"``A_CMD_DEFAULT`` \(([\d.]+) m/s\^2\)", " ".join(catch.__doc__.split())),
    }
    for where, found in quotes.items():
        assert found, f"{where} no longer quotes the default clamp"
        assert {float(v) for v in found} == {d.A_CMD_DEFAULT}, (where, found)


def test_the_gear_play_figures_quoted_are_the_commissionings_and_identifications() -> None:
    # docs/parameters.md, "The wheel side in the measurement" and "Identifying the pendulum on a
    # cart with play": the clamp for a cart with play, its range, and the identification's low-pass
    from host.operate import commission as C
    from host.studies import identify as I

    doc = _text("docs/parameters.md")
    m = re.search(r"`VERIFY_PLAY_MAX` \(([\d.]+) mm\), up to `PLAY_A_CMD_MAX` \(([\d.]+) mm\), with the clamp "
                  r"`PLAY_A_CMD` = ([\d.]+) m/s", doc)
    assert m, "docs/parameters.md no longer states the clamp for a cart with gear play"
    assert (float(m.group(1)) * 1e-3, float(m.group(2)) * 1e-3, float(m.group(3))) == (
        C.VERIFY_PLAY_MAX, C.PLAY_A_CMD_MAX, C.PLAY_A_CMD)
    m = re.search(r"until that term is ([\d.]+) m/s² \(`PLAY_XDD`\), at least ([\d.]+) Hz", doc)
    assert m, "docs/parameters.md no longer states the identification's low-pass for gear play"
    assert (float(m.group(1)), float(m.group(2))) == (I.PLAY_XDD, I.FC_MIN_HZ)


def test_the_board_parameters_the_gear_play_docs_name_are_the_firmwares() -> None:
    # docs/parameters.md names the two board parameters of a cart with play and their units
    from firmware import msgtable as T

    doc = _text("docs/parameters.md")
    units = {p[1]: p[2] for p in T.PARAMS}
    m = re.search(r"\(board parameter `gear_play`, encoder counts;", doc)
    assert m and units["gear_play"] == "count"
    m = re.search(r"\(board parameter `cart_coulomb`, 0\.01 N;", doc)
    assert m and units["cart_coulomb"] == "cN"


def test_the_wheel_side_figures_quoted_are_the_identifications() -> None:
    # docs/parameters.md, "The wheel side of the balancing run": the cart speed's low-pass and passes
    from host.studies import identify as I

    doc = _text("docs/parameters.md")
    m = re.search(r"wheel side's own through a ([\d.]+) Hz low-pass \((\w+) passes", doc)
    assert m, "docs/parameters.md no longer states how wheel_side takes the cart's speed"
    words = {"one": 1, "two": 2, "three": 3, "four": 4, "five": 5}
    assert (float(m.group(1)), words.get(m.group(2), m.group(2))) == (I.WHEEL_V_HZ, I.WHEEL_ITER)


def test_the_pot_gain_figures_quoted_are_identifys() -> None:
    # docs/parameters.md, "The pot's gain near upright": the windows, where the gain is used, the
    # interval where it is not
    from host.studies import identify as I

    doc = _text("docs/parameters.md")
    m = re.search(r"integrated twice over ([\d.]+) s windows\s+\(`POT_WIN_S`\)", doc)
    assert m and float(m.group(1)) == I.POT_WIN_S, "docs/parameters.md no longer states pot_gain's windows"
    m = re.search(r"resolved \(within (\d+) % of 1, its 95 % half-width under (\d+) %", doc)
    assert m and (int(m.group(1)), int(m.group(2))) == (round(100 * I.POT_GAIN_MAX), round(100 * I.POT_GAIN_CI))
    m = re.search(r"a pot's usual ±([\d.]+) % \(`POT_GAIN_PRIOR`", doc)
    assert m and float(m.group(1)) == round(100 * I.POT_GAIN_PRIOR, 1)


def test_the_set_point_ramp_quoted_is_commissions() -> None:
    # the README's commission stage table and its paragraph on what commission sets quote the
    # ramp of the robot file it writes (host.operate.commission.REF_RATE), and the board parameter's
    # unit is the message table's
    from firmware import msgtable as T
    from host.operate.commission import REF_RATE

    from host.operate.commission import PLAY_A_CMD_MAX, VERIFY_PLAY_MAX

    want = (REF_RATE[0], 1e3 * VERIFY_PLAY_MAX, REF_RATE[1], 1e3 * PLAY_A_CMD_MAX)
    readme = _text("README.md")
    m = re.search(r"ramps a new set-point at ([\d.]+) m/s up to ([\d.]+) mm of gear play, at ([\d.]+) m/s beyond "
                  r"([\d.]+) mm, at once between \(`loop\.ref_rate`", readme)
    assert m, "README's identify stage no longer states the set-point ramp"
    assert tuple(float(g) for g in m.groups()) == want
    m = re.search(r"the board parameter `ref_rate_mm_s` from the robot file's `loop\.ref_rate` \(([\d.]+) m/s up to "
                  r"([\d.]+) mm of gear play, ([\d.]+) m/s beyond ([\d.]+) mm:", readme)
    assert m, "README no longer says what sets ref_rate_mm_s"
    assert tuple(float(g) for g in m.groups()) == want
    units = {p[1]: p[2] for p in T.PARAMS}
    assert units["ref_rate_mm_s"] == "mm/s"
