"""Parameter files: the default robot loads; bad files name the offending key."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest

from sim.params import ParamError, load_params, params_from_dict

DEFAULT = Path(__file__).resolve().parent.parent / "sim" / "robot.toml"


def _text() -> str:
    return DEFAULT.read_text()


def test_default_robot_derives_geometry() -> None:
    p = load_params()
    assert p.m == pytest.approx(0.216)
    # centre of mass from the geometry (Table 2.1 rounds it to 0.24)
    assert p.L == pytest.approx(0.242612, rel=1e-5)
    # eq. (2.10) with L_cam = 0.0449 m; Table 2.1 prints 0.00128 (a factor-10 typo)
    assert p.I == pytest.approx(0.0128110, rel=1e-4)


@pytest.mark.parametrize(
    ("old", "new", "key"),
    [
        ("M = 0.5 ", "M = -0.5 ", "cart.M"),
        ("L_shaft = 0.3 ", "L_shaft = 0.0 ", "pendulum.L_shaft"),
        ("g = 9.8 ", 'g = "nine" ', "environment.g"),
        ("enc_cpr = 1200 ", "enc_cpr = 12.5 ", "sensors.enc_cpr"),
        ("pot_offset = 2048 ", "pot_offset = 5000 ", "sensors.pot_offset"),
        ("b = 0.1 ", "b = nan ", "cart.b"),
        ("M = 0.5 ", "Mass = 0.5 ", "cart.Mass"),
    ],
)
def test_bad_value_names_the_key(tmp_path: Path, old: str, new: str, key: str) -> None:
    bad = tmp_path / "bad.toml"
    assert old in _text()
    bad.write_text(_text().replace(old, new))
    with pytest.raises(ParamError) as exc:
        load_params(bad)
    assert exc.value.key == key
    assert key in str(exc.value)


def test_missing_key_is_named(tmp_path: Path) -> None:
    bad = tmp_path / "missing.toml"
    bad.write_text("\n".join(line for line in _text().splitlines() if not line.startswith("kt")))
    with pytest.raises(ParamError, match="motor.kt"):
        load_params(bad)


def test_unreadable_and_invalid_toml(tmp_path: Path) -> None:
    with pytest.raises(ParamError, match="cannot read"):
        load_params(tmp_path / "nope.toml")
    broken = tmp_path / "broken.toml"
    broken.write_text("[cart\nM = 1")
    with pytest.raises(ParamError, match="not valid TOML"):
        load_params(broken)


def test_unknown_section() -> None:
    with pytest.raises(ParamError, match="unknown section"):
        params_from_dict({"carts": {"M": 1.0}})


def test_replace_revalidates() -> None:
    p = load_params()
    assert p.replace(M=1.0).M == 1.0
    with pytest.raises(ParamError, match="cart.M"):
        p.replace(M=-1.0)
    with pytest.raises(ParamError):
        p.replace(nonsense=1.0)
    assert math.isclose(p.replace(L_cm=0.24).L, 0.24)


def test_cli_reports_bad_file_in_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(_text().replace("M = 0.5 ", "M = -1 "))
    proc = subprocess.run(
        [sys.executable, "-m", "host.cli.main", "simulate", "--open-loop", "--params", str(bad), "--csv", str(tmp_path / "o.csv")],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "cart.M" in proc.stderr
