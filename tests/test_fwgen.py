"""The firmware build room (host/boards/fwgen): the viper builds are generated from the plain code.

firmware/fastpath.py, fasttick.py, fastcan.py and fastlink.py are rendered from the readable
methods by AST transforms (tests/test_generated.py fails when a committed file is stale); here:
the transforms themselves -- a toy class's method rewritten on a slot array and run under the
unix port's real viper equals the plain method, an edit of a plain method shows up in the
rendered build, and what the transform cannot express is refused with a clear error; the CAN
and link builds compile with their names and signatures, render the same twice, and the
generated CRC equals crc32.Crc32 under real viper (allocation-free) and zlib under CPython.
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


# ---- the link-side builds: firmware/fastcan.py and fastlink.py (host/boards/fwgen/fastcan.py, fastlink.py) ----

def _top_functions(text: str) -> dict[str, ast.FunctionDef]:
    return {n.name: n for n in ast.parse(text).body if isinstance(n, ast.FunctionDef)}


def test_the_can_and_link_builds_compile_with_their_names_and_render_the_same_twice() -> None:
    from host.boards.fwgen.fastcan import render_fastcan
    from host.boards.fwgen.fastlink import render_fastlink
    for render, sigs in ((render_fastcan, {"pack_viper": ["codes", "nfields", "vals", "voff", "mid", "buf", "off"],
                                           "frame_viper": ["codes", "nfields", "vals", "voff", "mid", "q", "cid"]}),
                         (render_fastlink, {"telem_viper": ["arr", "t", "xf", "o", "vh", "ref", "u"],
                                            "crc32_low30": ["th", "tl", "mid", "buf", "off", "n"]})):
        text = render()
        assert render() == text  # deterministic
        compile(text, render.__name__, "exec")
        fns = _top_functions(text)
        assert set(sigs) <= set(fns), render.__name__
        for name, args in sigs.items():
            fn = fns[name]
            assert [a.arg for a in fn.args.args] == args, name
            assert [unparse(d) for d in fn.decorator_list] == ["micropython.viper"], name
            assert "self" not in unparse(fn), name
    # frame_viper packs inline (no viper-to-viper call) and writes link_can._fill's id bytes
    frame = unparse(_top_functions(render_fastcan())["frame_viper"])
    assert "pack_viper" not in frame and "B[1] = cid >> 3" in frame and "B[5] = n" in frame


def test_the_generated_crc_equals_crc32_under_real_viper_and_allocates_nothing() -> None:
    code = textwrap.dedent("""
        import micropython
        from firmware import crc32
        from firmware.fastlink import crc32_low30
        c = crc32.Crc32()
        bad = 0
        seed = 11
        buf = bytearray(64)
        for i in range(300):
            for k in range(64):
                seed = (seed * 1103515245 + 12345) & 0x7FFFFFFF
                buf[k] = (seed >> 8) & 0xFF
            mid = i & 0x1F
            off = i % 9
            n = i % 40
            c.start()
            c.byte(mid)
            c.feed(buf, off, n)
            if crc32_low30(c.th, c.tl, mid, buf, off, n) != c.low30():
                bad += 1
        micropython.heap_lock()
        try:
            for k in range(200):
                crc32_low30(c.th, c.tl, 5, buf, 2, 12)
            ok = 1
        except MemoryError:
            ok = 0
        micropython.heap_unlock()
        print('bad', bad, 'alloc_free', ok)
    """)
    assert run_unix(code, timeout=60).split() == ["bad", "0", "alloc_free", "1"]


def test_the_cpython_fallback_crc_equals_zlib() -> None:
    import zlib

    from firmware import crc32
    from firmware.fastlink import crc32_low30
    c = crc32.Crc32()
    data = bytes(range(7, 90))
    for mid, off, n in ((0, 0, 0), (3, 1, 10), (31, 5, 60)):
        assert crc32_low30(c.th, c.tl, mid, data, off, n) == zlib.crc32(bytes([mid]) + data[off:off + n]) & 0x3FFFFFFF


def _firmware_copy(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    fw = tmp_path / "firmware"
    fw.mkdir()
    for p in layout.FIRMWARE.glob("*.py"):
        (fw / p.name).write_text(p.read_text())
    import host.boards.fwgen.fastcan as FC
    import host.boards.fwgen.fastframe as FF
    import host.boards.fwgen.fastlink as FL
    for mod in (FF, FC, FL):
        monkeypatch.setattr(mod, "FIRMWARE", fw)
    return fw


def _edit(path: Path, old: str, new: str) -> str:
    # one occurrence of old in the file replaced by new; -> the text before the edit
    text = path.read_text()
    assert text.count(old) == 1, (path.name, old)
    path.write_text(text.replace(old, new))
    return text


def test_an_edit_of_the_plain_link_code_changes_the_build(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from host.boards.fwgen.fastcan import render_fastcan
    from host.boards.fwgen.fastlink import render_fastlink
    can0, link0 = render_fastcan(), render_fastlink()
    fw = _firmware_copy(monkeypatch, tmp_path)
    _edit(fw / "link_can.py", "        q[3] = 0\n", "        q[3] = 1\n")
    _edit(fw / "app.py", "(1 << (s - 1))) >> s\n", "(1 << (s - 2))) >> s\n")
    _edit(fw / "crc32.py", "            hi = (hi >> 8) ^ th[k]\n", "            hi = (hi >> 8) ^ th[k] ^ 1\n")
    can1, link1 = render_fastcan(), render_fastlink()
    assert "B[3] = 1" in can1 and "B[3] = 1" not in can0
    assert link1.count("(1 << (s - 2))") == 1 and "(1 << (s - 2))" not in link0
    assert "hi = (hi >> 8) ^ th[k] ^ 1" in link1


def test_what_the_link_builds_cannot_follow_is_refused(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from host.boards.fwgen.fastcan import render_fastcan
    from host.boards.fwgen.fastlink import render_fastlink
    fw = _firmware_copy(monkeypatch, tmp_path)
    lc = _edit(fw / "link_can.py", "cid = ((self.node & 0x3F) << 5) | (mid & 0x1F)\n        q[1]",
               "cid = ((self.node & 0x1F) << 5) | (mid & 0x1F)\n        q[1]")
    with pytest.raises(ValueError, match="id differs from the one send passes"):
        render_fastcan()
    (fw / "link_can.py").write_text(lc)
    render_fastcan()
    _edit(fw / "crc32.py", "        self.hi = (hi >> 8) ^ self.th[k]\n",
          "        self.hi = (hi >> 8) ^ self.th[k]\n        self.lo ^= lo\n")
    with pytest.raises(ValueError, match="reads the local lo after storing its attribute"):
        render_fastlink()
