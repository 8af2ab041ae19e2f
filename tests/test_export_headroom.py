"""Fixed-point export (host/design/export.py): the headroom proof, the table layout and the CLI."""

from __future__ import annotations

import math
import struct

import pytest

from host.design import export as ex
from host.design.discrete import controller_ss
from sim.params import load_params

SMALL = 2**30 - 1


@pytest.fixture(scope="module")
def fd():
    return ex.export()


def _t(fd, name):
    return fd.tables[name]


def test_every_row_fits_a_small_int(fd) -> None:
    for r in fd.rows:
        assert r.worst <= SMALL - ex.MARGIN, r.name
        assert 0 <= r.shift <= ex.SHIFT_MAX


def test_headroom_recomputed_from_the_tables(fd) -> None:
    # independent of Row: rebuild each accumulator's bound from the flat tables
    d = fd.delay
    LIM = _t(fd, "LIM")
    (ULIM,), (RLIM,), (ILIM,) = _t(fd, "ULIM"), _t(fd, "RLIM"), _t(fd, "ILIM")
    M, SM = _t(fd, "M"), _t(fd, "SM")
    for i in range(4):
        worst = abs(M[2 * i]) * 2 * LIM[0] + abs(M[2 * i + 1]) * 2 * LIM[2] + 2 ** SM[i]
        assert worst <= SMALL
        # the state after the filter: |p| + |acc >> S| stays small too
        assert LIM[i] + (worst >> SM[i]) <= SMALL
    force = sum(abs(g) * b for g, b in zip(_t(fd, "KF"), LIM)) + sum(abs(g) * ULIM for g in _t(fd, "KB"))
    force += abs(_t(fd, "KR")[0]) * RLIM + abs(_t(fd, "KI")[0]) * ILIM + 2 ** (_t(fd, "SK")[0] - 1)
    assert force <= SMALL
    speed = sum(abs(g) * b for g, b in zip(_t(fd, "KV"), LIM)) + sum(abs(g) * ULIM for g in _t(fd, "KVB"))
    assert speed + 2 ** (_t(fd, "SKV")[0] - 1) <= SMALL
    AD, BD, SA = _t(fd, "AD"), _t(fd, "BD"), _t(fd, "SA")
    for i in range(4):
        worst = sum(abs(AD[4 * i + j]) * LIM[j] for j in range(4)) + abs(BD[i]) * ULIM + 2 ** SA[i]
        assert worst <= SMALL
    KDU, KDV, SD, DB = _t(fd, "MOT")
    assert abs(KDU) * ULIM + abs(KDV) * LIM[1] + 2 ** (SD - 1) <= SMALL and 0 <= DB <= 4096
    RMUL, RDIV = _t(fd, "REF")
    assert RMUL * ex.REF_UM_MAX + RDIV // 2 <= SMALL
    assert RDIV * 1e-9 / RMUL * 1e3 == pytest.approx(fd.lsb["x"], rel=1e-4)
    # the integrator input: r - x, then the running sum, stay small
    assert RLIM + LIM[0] + 32 <= SMALL and ILIM + ((RLIM + LIM[0]) >> ex.INTEG_SHIFT) + 1 <= SMALL
    # measurement conversion: clamped counts shifted into state LSB stay within the limits
    YX, YP = _t(fd, "YLIM")
    QX, QP = _t(fd, "FMT")[:2]
    assert YX << QX <= LIM[0] and YP << QP <= LIM[2]
    assert len(fd.flat()) == fd.tables["HDR"][2] and fd.tables["HDR"][1] == d


def test_scales_and_limits(fd) -> None:
    p = fd.params
    assert fd.lsb["x"] * _t(fd, "LIM")[0] == pytest.approx(2 * p.track, rel=1e-3)
    assert fd.lsb["phi"] * _t(fd, "LIM")[2] == pytest.approx(math.pi / 2, rel=1e-3)
    assert fd.lsb["u"] * _t(fd, "ULIM")[0] == pytest.approx(fd.ctrl.u_max, rel=1e-3)
    # the resolution of the states is finer than the sensors'
    assert fd.lsb["x"] < 2 * math.pi * p.r_wheel / p.enc_cpr
    assert fd.lsb["phi"] < p.pot_range / 2**p.adc_bits


def _exact_rows(fd):
    """Every gain table beside the real coefficient it quantises (in output LSB per input
    LSB) and the shift it was quantised at -- rebuilt here from the float controller and the
    formats, independent of export's Row objects."""
    import numpy as np

    c, p, s = fd.ctrl, fd.params, fd.lsb
    st = [s["x"], s["xdot"], s["phi"], s["phidot"]]
    meas = [s["x"], s["phi"]]
    su, d = s["u"], fd.delay
    out = []
    SM = _t(fd, "SM")
    for i in range(4):
        out.append((f"M[{i}]", _t(fd, "M")[2 * i:2 * i + 2], [c.M[i, j] * meas[j] / st[i] for j in range(2)], SM[i]))
    SK = _t(fd, "SK")[0]
    out.append(("KF", _t(fd, "KF"), [-c.Kf[0][j] * st[j] / su for j in range(4)], SK))
    out.append(("KB", _t(fd, "KB"), [-c.kb[i] for i in range(d)], SK))
    out.append(("KR", _t(fd, "KR"), [c.kr * s["x"] / su], SK))
    out.append(("KI", _t(fd, "KI"), [math.copysign(fd.ki, c.kr) * s["integ"] / su], SK))
    Phi = np.linalg.matrix_power(c.Ad, d)
    gam = [(np.linalg.matrix_power(c.Ad, d - 1 - i) @ c.Bd)[1, 0] for i in range(d)]
    SKV = _t(fd, "SKV")[0]
    out.append(("KV", _t(fd, "KV"), [Phi[1, j] * st[j] / st[1] for j in range(4)], SKV))
    out.append(("KVB", _t(fd, "KVB"), [g * su / st[1] for g in gam], SKV))
    Adm = c.Ad - np.eye(4)
    SA = _t(fd, "SA")
    for i in range(4):
        out.append((f"AD[{i}]", _t(fd, "AD")[4 * i:4 * i + 4], [Adm[i, j] * st[j] / st[i] for j in range(4)], SA[i]))
        out.append((f"BD[{i}]", [_t(fd, "BD")[i]], [c.Bd[i, 0] * su / st[i]], SA[i]))
    KDU, KDV, SD, _ = _t(fd, "MOT")
    duty_per_volt = ex.DUTY_MAX / p.V_supply
    out.append(("MOT", [KDU, KDV], [p.R * p.r_wheel / (p.n_motors * p.gear * p.kt) * duty_per_volt * su,
                                    p.kt * p.gear / p.r_wheel * duty_per_volt * st[1]], SD))
    TNUM, TSH = _t(fd, "TILT")
    out.append(("TILT", [TNUM], [1e-3 / (p.pot_range / 2**p.adc_bits)], TSH))
    *tel, tsh = _t(fd, "TEL")
    out.append(("TEL", tel, [v / u for v, u in zip(st + [su], ex.TELEM_UNITS)], tsh))
    return out


def test_every_gain_row_is_its_coefficient_rounded_at_its_shift(fd) -> None:
    # a gain g at shift S stands for g / 2**S; rounding to nearest puts it within half a
    # count of coefficient * 2**S, i.e. within 2**-(S+1) of the coefficient -- the bound
    # follows from each row's own shift.  Every table is checked, the force row's stored-force
    # gains KB too (integers 34-36 at shift 10: up to 1 % off the coefficient, which is the
    # rounding, not a defect).  A sign flip, a gain off by one count more than rounding, or a
    # shift off by one (a factor 2 against the coefficient) fails here.
    names = set()
    for name, gains, exact, shift in _exact_rows(fd):
        names.add(name.split("[")[0])
        assert len(gains) == len(exact), name
        for j, (g, e) in enumerate(zip(gains, exact)):
            # 1e-9 relative: float round-off of the coefficient itself
            assert abs(g - e * 2**shift) <= 0.5 + 1e-9 * abs(e * 2**shift), (name, j, g, e * 2**shift)
    assert names == {"M", "KF", "KB", "KR", "KI", "KV", "KVB", "AD", "BD", "MOT", "TILT", "TEL"}
    # the rows kept at 0: the integral gain is off in the default design, not lost to rounding
    assert _t(fd, "KI") == [0] and fd.ki == 0.0
    fdi = ex.export(ki=20.0)
    for name, gains, exact, shift in _exact_rows(fdi):
        if name == "KI":
            assert gains[0] != 0 and abs(gains[0] - exact[0] * 2**shift) <= 0.5 + 1e-9 * abs(exact[0] * 2**shift)


def test_gains_reproduce_the_float_controller(fd) -> None:
    c = fd.ctrl
    s = fd.lsb
    SK = _t(fd, "SK")[0]
    Kf = [-g / 2**SK * s["u"] / s[k] for g, k in zip(_t(fd, "KF"), ("x", "xdot", "phi", "phidot"))]
    # rounding at shift 10 leaves each gain within half a count: relative 0.5/248 = 2.0e-3
    # for the smallest (KF[0] = 248 counts; KF runs 248..10191).  Measured 3.2e-4 at most
    assert Kf == pytest.approx(list(c.Kf[0]), rel=2e-3)
    assert _t(fd, "KR")[0] / 2**SK * s["u"] / s["x"] == pytest.approx(c.kr, rel=2e-3)


def test_blob_crc_and_render(fd) -> None:
    blob = fd.blob()
    flat = fd.flat()
    assert struct.unpack(f"<{len(flat)}i", blob) == tuple(flat)
    assert ex.crc16(b"123456789") == 0x29B1
    text = ex.render(fd)
    assert "do not edit" in text.splitlines()[0] and "host/design/export.py" in text.splitlines()[0]
    assert f"CRC = const(0x{fd.crc():04X})" in text
    ns: dict = {}
    exec(compile(text, "gains.py", "exec"), ns)
    assert list(ns["FLAT"]) == flat and ns["LENGTH"] == len(flat) and ns["DELAY"] == fd.delay
    assert [n for n, _ in ns["LAYOUT"]] == [n for n, _ in ex.LAYOUT]


def test_default_render_is_deterministic() -> None:
    assert ex.render_default() == ex.render_default()


def test_integral_gain_sign_follows_kr() -> None:
    fd = ex.export(ki=20.0)
    assert fd.tables["KI"][0] != 0 and (fd.tables["KI"][0] > 0) == (fd.tables["KR"][0] > 0)


@pytest.mark.parametrize("kwargs", [dict(ki=-1.0), dict(ki=math.inf), dict(deadband=-1), dict(deadband=1.5)])
def test_bad_arguments(kwargs) -> None:
    with pytest.raises(ValueError):
        ex.export(**kwargs)


def test_a_row_that_cannot_fit_is_an_error() -> None:
    with pytest.raises(ValueError, match="row big"):
        ex._row("big", [2.0**20], [2**12])


def test_other_rates_and_designs_export() -> None:
    p = load_params()
    for rate in (250, 1000):
        fd = ex.export(p, controller_ss(p, rate=rate))
        assert fd.tables["RATE"] == [rate]
        assert all(r.worst <= SMALL for r in fd.rows)


def test_cli_export(tmp_path) -> None:
    from host.cli import main as cli

    out = tmp_path / "g.py"
    blob = tmp_path / "g.bin"
    assert cli.main(["export", "--out", str(out), "--blob", str(blob), "--ki", "5"]) == 0
    assert "do not edit" in out.read_text()
    assert len(blob.read_bytes()) % 4 == 0
    assert cli.main(["export", "--design", "place", "--out", str(out)]) == 0
    assert "design=place" in out.read_text()
    assert cli.main(["export", "--design", "place", "--Q", "1", "0", "1", "0"]) == 2  # bad flag combination: exit 2


@pytest.mark.parametrize("v_limit, w_limit, v_want, w_want",
                         [(None, None, 16.0, 120.0), (3.6, 30.0, 3.6, 30.0)])
def test_estimate_limits_default_and_option(v_limit, w_limit, v_want, w_want) -> None:
    import fwharness as H

    p = load_params()
    fd = ex.export(p, v_limit=v_limit, w_limit=w_limit)
    assert (ex.V_LIMIT, ex.W_LIMIT) == (16.0, 120.0)
    assert all(r.worst <= SMALL for r in fd.rows)
    assert fd.lsb["xdot"] * fd.tables["LIM"][1] == pytest.approx(v_want, rel=1e-3)
    assert fd.lsb["phidot"] * fd.tables["LIM"][3] == pytest.approx(w_want, rel=1e-3)
    # telemetry conversions use the table's own shift and still fit
    *tel, tsh = fd.tables["TEL"]
    bounds = fd.tables["LIM"] + fd.tables["ULIM"]
    assert all(abs(g) * b + 2 ** (tsh - 1) <= SMALL for g, b in zip(tel, bounds))
    s = H.measurements(p, fd, [0, 0, 0.1, 0], 2.0)
    u, _ = H.py_controller_run(fd, s.yx, s.yp, s.r)
    # within 1.5 % of the force clamp, the bound of test_firmware_fixed_vs_float (measured
    # 0.0194 N with the 3.6 m/s / 30 rad/s clamps, 0.0297 N with the defaults, of 2.88 N)
    from host.design.discrete import force_clamp

    err = max(abs(a * fd.lsb["u"] - b) for a, b in zip(u, s.u_float))
    assert err <= 0.015 * force_clamp(p), err
    with pytest.raises(ValueError):
        ex.export(p, v_limit=-1.0)
