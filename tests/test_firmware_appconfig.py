"""App's two contracts declared once: the HAL's optional capabilities (``firmware/hal_base.Hal``,
``None``: absent) and the config keys with their defaults and ranges (``firmware.appconfig.CONFIG``, read
through ``cfg_value``).  An unknown key or a value out of range is refused with one line naming the
key, under CPython and the MicroPython unix port alike; a HAL with only the required methods runs."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import fwharness as H
from firmware import board
from firmware import msgtable as T
from firmware.app import App
from firmware.appconfig import CONFIG, cfg_value
from firmware.hal_base import Hal
from firmware.hal_hil import HilHal
from firmware.supervisor import DISARMED
from host.boards.mpyrun import run_unix

ROOT = Path(__file__).resolve().parents[1]


def _bare_hal() -> H.StandInHal:
    # the shared stand-in: the required methods only, every optional capability the base
    # class's None; its duty starts at 7, so a test sees the app drive it to 0
    return H.StandInHal(duty=7)


@pytest.mark.parametrize("cfg, key", [
    ({"stall_msec": 10}, "stall_msec"),  # a misspelt key
    ({"stall_ms": -1}, "stall_ms"),
    ({"stall_duty": 40000}, "stall_duty"),
    ({"adc_sign": 2}, "adc_sign"),
    ({"wdt_ms": 9000}, "wdt_ms"),  # longer than the RP2040's watchdog can time
    ({"boot": 256}, "boot"),
    ({"pot_offset": "2048"}, "pot_offset"),  # not an integer
    ({"emitter": "jit"}, "emitter"),  # emitter.check's own message
])
def test_an_unknown_key_or_a_value_out_of_range_is_refused_naming_the_key(cfg: dict, key: str) -> None:
    with pytest.raises(ValueError, match=f"^config {key}: ") as e:
        App(_bare_hal(), config=cfg)
    assert "\n" not in str(e.value)


def test_every_key_has_its_default_and_a_range_holding_it() -> None:
    names = [k for k, *_ in CONFIG]
    assert len(names) == len(set(names)), "a CONFIG key twice"
    for k, d, lo, hi in CONFIG:
        assert cfg_value({}, k) == d
        if lo is not None:
            assert lo <= hi, k
            assert d is None or lo <= d <= hi, k
            assert cfg_value({k: lo}, k) == lo and cfg_value({k: hi}, k) == hi


def test_the_boards_config_and_parameter_names_are_accepted() -> None:
    # board.config() is what main.py hands the app; a msgtable PARAMS name overrides a
    # parameter unchecked (watchdog_ms=0: the watchdog off, bench/tests)
    app = App(_bare_hal(), config={**board.config(), "watchdog_ms": 0, "max_duty": 1000})
    assert app.params[T.P_WATCHDOG_MS] == 0 and app.motor.max_duty == 1000
    assert app.wdt_ms == board.WDT_MS and app.vsup_nom == board.VSUP_NOMINAL_MV


def test_a_hal_without_the_optional_capabilities_runs() -> None:
    hal = _bare_hal()
    app = App(hal, config={"watchdog_ms": 0, "stall_ms": 0, "epoch": 1})
    assert app._set_enable is None and app._estop is None and app._read_vsup is None
    assert not app._has_open and not app._has_frames
    app.run(50, lock=False)
    assert app.tick == 50 and app.sup.state == DISARMED and hal.duty == 0


def test_the_hals_derive_from_the_declared_base() -> None:
    assert isinstance(HilHal(None), Hal) and isinstance(H.StandInHal(), Hal)
    # HalPico imports machine/rp2 (the board only): its class line, read from the source
    tree = ast.parse((ROOT / "firmware" / "hal_pico.py").read_text())
    cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "HalPico")
    assert [ast.unparse(b) for b in cls.bases] == ["Hal"]
    # the base declares every optional capability as None, nothing else
    declared = {k: v for k, v in vars(Hal).items() if not k.startswith("__")}
    assert declared and set(declared.values()) == {None}


def _probes(modules: tuple[str, ...], obj: str) -> list[str]:
    # hasattr/getattr calls on an expression naming obj, in firmware/<module>.py
    out = []
    for mod in modules:
        tree = ast.parse((ROOT / "firmware" / f"{mod}.py").read_text())
        out += [f"{mod}: {ast.unparse(n)}" for n in ast.walk(tree) if isinstance(n, ast.Call)
                and isinstance(n.func, ast.Name) and n.func.id in ("hasattr", "getattr")
                and obj in ast.unparse(n.args[0])]
    return out


def test_the_app_reads_the_hal_without_probing_it() -> None:
    # no hasattr/getattr on the HAL in the app and its parts: the capabilities are the base
    # class's attributes
    assert _probes(("app", "appparams", "appstatus", "appstore", "apptable"), "hal") == []


def test_the_dispatcher_reads_its_target_without_probing_it() -> None:
    # commands.Target declares each optional capability as None; the dispatcher reads the
    # attributes, never hasattr/getattr on the target, and the app's parts override every one
    from firmware import commands

    assert _probes(("commands",), "target") == []
    declared = {k: v for k, v in vars(commands.Target).items() if not k.startswith("__")}
    assert declared and set(declared.values()) == {None}
    assert App.__mro__[-2] is commands.Target  # last: no part's method hidden by a None
    missing = [k for k in declared if getattr(App, k) is None]
    assert missing == []
    bare = commands.Dispatcher(commands.Target(), None, object())
    assert bare._save is None and bare._status is None and bare._feed is None


def test_the_unix_port_refuses_and_runs_alike() -> None:
    # MicroPython's bool is no int subclass: the boolean keys must still pass there
    code = H.FAKE_HAL + """
from firmware.app import App
for cfg in ({'stall_msec': 1}, {'stall_ms': 70000}, {'deadline': 2}):
    try:
        App(Hal(), config=cfg)
        print('accepted')
    except ValueError as e:
        print(str(e).split(':')[0])
app = App(Hal(), config={'deadline': False, 'backemf': True, 'watchdog_ms': 0, 'stall_ms': 0})
app.run(20)
print('ticks', app.tick)
"""
    out = run_unix(code).split("\n")
    assert out[:4] == ["config stall_msec", "config stall_ms", "config deadline", "ticks 20"]
