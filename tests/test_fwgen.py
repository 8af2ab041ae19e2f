"""The firmware build room (host/boards/fwgen): the viper builds are generated from the plain code.

firmware/fastpath.py and firmware/fasttick.py are rendered from the readable methods by AST
transforms (tests/test_generated.py fails when a committed file is stale); here: the
transforms themselves -- a toy class's method rewritten on a slot array and run under the
unix port's real viper equals the plain method, an edit of a plain method shows up in the
rendered build, and what the transform cannot express is refused with a clear error.
"""

from __future__ import annotations

import ast
import textwrap
from pathlib import Path

import pytest

from host.boards.fwgen import layout
from host.boards.fwgen.fasttick import render_fasttick
from host.boards.fwgen.viper import SlotObject, find_method, slot_viper_function, unparse
from host.boards.mpyrun import run_unix

TOY = textwrap.dedent("""
    _LIM = const(1000)

    class Toy:
        def __init__(self):
            self.acc = 0
            self.n = 0
            self.hit = False
            self.gain = 3

        def update(self, x):
            v = self.acc + self.gain * x
            if v > _LIM:
                v = _LIM
            elif v < -_LIM:
                v = -_LIM
            self.acc = v
            self.n += 1
            self.hit = v == _LIM or v == -_LIM
            return -self.gain < x < self.gain
""")

TOY_STATE = SlotObject("TY", (("acc", "i"), ("n", "u"), ("hit", "b"), ("gain", "i")))


def _toy_build(tmp_path: Path) -> str:
    src = tmp_path / "toy.py"
    src.write_text(TOY)
    fn, extra, bool_ret, _ = slot_viper_function(find_method(src, "Toy", "update"), "toy_update", TOY_STATE)
    assert extra == [] and bool_ret is False  # returns a comparison, not a literal flag
    consts = "".join(f"{TOY_STATE.const(a)} = const({i})\n" for i, (a, _) in enumerate(TOY_STATE.slots))
    return consts + unparse(fn) + "\n"  # (_LIM: the source's, above)


def test_a_slot_build_equals_the_plain_method_under_real_viper(tmp_path: Path) -> None:
    code = ("import micropython\nfrom micropython import const\nfrom array import array\n"
            + TOY + _toy_build(tmp_path) + textwrap.dedent("""
        a = Toy()
        S = array('i', [0, 0, 0, 3])
        bad = 0
        seed = 7
        for i in range(3000):
            seed = (seed * 1103515245 + 12345) & 0x7FFFFFFF
            x = (seed >> 8) % 401 - 200
            ra = a.update(x)
            rb = toy_update(S, x)
            if int(ra) != int(rb) or a.acc != S[0] or a.n != S[1] or int(a.hit) != S[2]:
                bad += 1
        print('bad', bad, a.n, a.acc)
    """))
    out = run_unix(code, timeout=60).split()
    assert out[0] == "bad" and out[1] == "0" and out[2] == "3000", out


def test_an_edit_of_a_plain_method_changes_the_build(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    # a copy of the firmware with Motor.duty's deadband step edited: the rendered build follows
    fw = tmp_path / "firmware"
    fw.mkdir()
    for p in layout.FIRMWARE.glob("*.py"):
        (fw / p.name).write_text(p.read_text())
    motor = fw / "motor.py"
    text = motor.read_text()
    assert "            d += self.deadband\n" in text
    motor.write_text(text.replace("            d += self.deadband\n", "            d += self.deadband + 1\n"))
    import host.boards.fwgen.fasttick as FT
    import host.boards.fwgen.step as ST
    before = render_fasttick()
    for mod in (layout, FT, ST):
        monkeypatch.setattr(mod, "FIRMWARE", fw)
    after = render_fasttick()
    assert before != after
    assert "d += (((S[_MO_DEADBAND] + sb) & msk) - sb) + 1" in after


def test_a_store_outside_the_slot_layout_is_refused(tmp_path: Path) -> None:
    src = tmp_path / "bad.py"
    src.write_text("class Bad:\n    def update(self, x):\n        self.other = x\n")
    with pytest.raises(ValueError, match="self.other, which is not in the slot layout"):
        slot_viper_function(find_method(src, "Bad", "update"), "bad_update", TOY_STATE)
    with pytest.raises(ValueError, match="class Bad has no method tick"):
        find_method(src, "Bad", "tick")


def test_the_generated_tick_holds_no_hand_written_part() -> None:
    text = render_fasttick()
    tree = ast.parse(text)
    names = {n.name for n in tree.body if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
    for part in layout.TICK_PARTS:
        assert part.cls + "V" in names
        assert {f for _, f in part.methods} <= names
    assert {"StepV", "PacerV", "SupplyV"} <= names
    # the module-level viper functions work on slot arrays: no object left in them
    viper = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.decorator_list]
    assert len(viper) == sum(len(p.methods) for p in layout.TICK_PARTS)
    assert "self" not in "".join(unparse(n) for n in viper)
