"""One of each on the host (issue 25 item 3): one fault table, one keepalive, one loss counter, one link.

The fault names of the CLI, ``upright board status`` and the dashboard are the protocol table's
(``msgtable.FAULTS``); every tool that keeps a board armed sends its host heartbeat through
:class:`host.link.clients.Keepalive`; HIL runs, the board recorder and the dashboard count lost
frames with :class:`host.hil.accounting.SeqAccount`; board tools and the dashboard share one
:class:`host.link.clients.Link` (a pump thread reads it, commands from other threads take what it delivers).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

from firmware import msgtable as T
from host.dashboard.hub import Hub
from host.hil.accounting import SeqAccount
from host.link import messages as M
from host.link.clients import Keepalive, Link
from host.link.keepalive import KEEPALIVE_BOARD_S, KEEPALIVE_MAX_S
from host.operate.board import Board, fault_names, fault_table
from host.operate.record import COLUMNS, TELEMETRY, Recorder

TS, TC, HB = M.BY_NAME["telem_state"], M.BY_NAME["telem_ctrl"], M.BY_NAME["heartbeat"]


class _Sent(Link):
    def __init__(self) -> None:
        super().__init__(check_identity=False)
        self.names: list[str] = []

    def _send(self, msg: M.Message, seq: int) -> None:
        self.names.append(msg.NAME)

    def _recv_internal(self, timeout):
        return []

    def _close(self) -> None:
        pass


def test_every_tool_names_the_faults_of_the_protocol_table(tmp_path: Path) -> None:
    assert fault_table() == {bit: (name, doc) for bit, name, doc in T.FAULTS}
    every = sum(bit for bit, _, _ in T.FAULTS)
    assert fault_names(every) == [name for _, name, _ in sorted(T.FAULTS)]
    assert fault_names(1 << 20) == ["bit20"]
    hub = Hub(_Sent(), {"mode": "test"}, tmp_path)
    try:
        assert hub.hello("p")["faults"] == [[b, n, d] for b, n, d in sorted(T.FAULTS)]
        hub.heartbeat = {"state": 3, "faults": 64 | 256}
        assert hub.status()["heartbeat"]["fault_names"] == ["stall", "deadline"]
    finally:
        hub.close()


def test_the_keepalive_sends_the_host_heartbeat_once_a_period() -> None:
    link = _Sent()
    k = Keepalive(link.send, period=0.125)  # times in exact binary fractions of a second
    assert [k.tick(t) for t in (10.0, 10.0625, 10.125, 10.1875, 10.25)] == [True, False, True, False, True]
    k.fed(10.3125)  # a set-point fed the watchdog: the next heartbeat is a period after it
    assert [k.tick(t) for t in (10.375, 10.4375)] == [False, True]
    assert link.names == ["host_heartbeat"] * 4 and k.sent == 4


def test_one_keepalive_per_link_beats_in_the_boards_time(tmp_path: Path) -> None:
    link = _Sent()
    board = Board(link, feed=False)
    hub = Hub(link, {"mode": "test"}, tmp_path)
    try:
        k = link.keepalive
        assert board._keepalive is k and hub._keepalive is k and hub.board._keepalive is k  # one object
    finally:
        hub.close()
    k = Keepalive(link.send, period=0.0625)
    assert k.period == 0.0625  # no board heartbeat seen: full speed
    for i in range(9):  # a board at 0.1x: 125 ms of its clock every 1.25 s of wall
        k.observe(125 * i, 10.0 + 1.25 * i)
    assert k.clock.speed == 0.1 and k.period == KEEPALIVE_BOARD_S / 0.1
    k.fed(30.0)
    assert [k.tick(t) for t in (30.125, 30.25, 30.375, 30.5)] == [False, True, False, True]  # every 250 ms of wall
    for i in range(9):  # a board that nearly stopped: never rarer than KEEPALIVE_MAX_S
        k.observe(1000 + i, 40.0 + i)
    assert k.period == KEEPALIVE_MAX_S
    # the link shows its keepalive every board heartbeat it reads
    n = len(link.keepalive.clock._seen)
    link._ingest([(HB(**{f.name: 0 for f in HB.FIELDS}), 7)])
    assert len(link.keepalive.clock._seen) == n + 1


def test_the_recorder_and_the_dashboard_record_the_same_columns(tmp_path: Path) -> None:
    from host.dashboard.hub import COLUMNS as DASH

    assert set(COLUMNS) <= set(DASH) and DASH[2:-1] == TELEMETRY == COLUMNS[2:]
    st, ct = TS(x=1000, xdot=0, phi=-20, phidot=0), TC(ref=2000, force=150, duty=-300, step_us=90)

    class _B:
        listeners: list = []

    rec = Recorder(_B(), tmp_path / "r.csv")
    hub = Hub(_Sent(), {"mode": "test"}, tmp_path)
    try:
        for seq in (1, 2, 4):
            for m in (st, ct):
                rec.board.listeners[0](m, seq, seq * 0.02)
                hub.on_message(m, seq)
        rec.close()
        assert rec.lost == hub.pairs.lost == 1 and rec.rows == hub.n == 3
        mine = dict(zip(DASH, hub.rows[-1]))
        import csv

        with open(tmp_path / "r.csv", newline="") as fh:
            last = list(csv.DictReader(fh))[-1]
        assert {k: float(last[k]) for k in COLUMNS if k != "t" and k not in ("state", "faults")} \
            == {k: float(mine[k]) for k in COLUMNS if k != "t" and k not in ("state", "faults")}
    finally:
        hub.close()


def test_the_loss_counter_is_bounded_and_exact_over_long_runs() -> None:
    a = SeqAccount()
    st, ct = TS(x=0, xdot=0, phi=0, phidot=0), TC(ref=0, force=0, duty=0, step_us=0)
    lost = 0
    for u in range(100_000):
        if u % 997 == 13:
            lost += 1
            continue
        a.add(st, u & 0xFF)
        if u % 1009 != 7:
            a.add(ct, u & 0xFF)
    assert a.lost == lost and a.events == 100_000 - lost
    assert a.half_pairs == sum(1 for u in range(100_000) if u % 1009 == 7 and u % 997 != 13)
    assert len(a._pair) <= 2 * SeqAccount.WINDOW + 1  # memory bounded
    a.add(st, (100_000 - 4) & 0xFF)  # a frame of 3 ticks ago again: late and a duplicate
    assert (a.reordered, a.duplicates, a.lost) == (1, 1, lost)


def test_the_recorder_counts_one_lost_frame_once(tmp_path: Path) -> None:
    class _B:
        listeners: list = []

    b = _B()
    b.listeners = []
    rec = Recorder(b, tmp_path / "r.csv")
    on = b.listeners[0]
    st, ct = TS(x=0, xdot=0, phi=0, phidot=0), TC(ref=0, force=0, duty=0, step_us=0)
    for seq in range(1, 8):
        if seq != 4:  # the TELEM_STATE of tick 4 is lost, its TELEM_CTRL arrives
            on(st, seq, seq * 0.02)
        on(ct, seq, seq * 0.02)
    rec.close()
    assert rec.rows == 6 and rec.lost == 1, rec.summary()


class _Board(Link):
    """A transport whose board answers every request after a while, seq for seq (one frame in flight)."""

    def __init__(self) -> None:
        super().__init__(check_identity=False)
        self.wire: list[tuple[M.Message, int]] = []
        self.cv = threading.Condition()

    def _send(self, msg: M.Message, seq: int) -> None:
        with self.cv:
            if msg.NAME == "param_get":
                self.wire.append((M.BY_NAME["param_value"](index=msg.index, value=40 + msg.index), seq))
            self.wire.append((TS(x=seq, xdot=0, phi=0, phidot=0), 200))  # periodic traffic in between
            self.cv.notify_all()

    def _recv_internal(self, timeout):
        with self.cv:
            if not self.wire:
                self.cv.wait(timeout)
            out, self.wire = self.wire, []
        return out


def test_one_link_is_shared_by_a_pump_thread_and_commands_from_others() -> None:
    link = _Board()
    link.share()
    seen: list[tuple[str, int | None]] = []
    stop = threading.Event()

    def pump() -> None:  # the dashboard's pump: reads every frame, hands on all but telemetry
        link.share(threading.current_thread())
        while not stop.is_set():
            m = link.recv(0.02)
            if m is not None:
                seen.append((m.NAME, link.last_seq))
                if m.NAME != "telem_state":
                    link.deliver(m, link.last_seq)

    t = threading.Thread(target=pump, daemon=True)
    t.start()
    try:
        # commands from two other threads, one at a time, each gets its own reply by seq
        got = []
        for idx in (1, 2):
            th = threading.Thread(target=lambda i=idx: got.append(link.param_get(i, timeout=2.0, retries=0)))
            th.start()
            th.join(5)
        assert sorted(got) == [41, 42]
        deadline = time.monotonic() + 2
        while len(seen) < 4 and time.monotonic() < deadline:
            time.sleep(0.01)
        names = [n for n, _ in seen]
        # the pump read every frame once (a delivered frame does not come back to it)
        assert names.count("param_value") == 2 and names.count("telem_state") == 2
        assert all(s == 200 for n, s in seen if n == "telem_state")  # its own last_seq, not a command's
        # a request's seq is known as a reply's while shared (the loss counter skips it)
        seq = link.send(M.BY_NAME["request"](msg_id=T.HEARTBEAT))
        assert link.is_reply(seq) and not link.is_reply(seq)
        # telemetry never reaches the commands' side: only delivered frames do
        link.discard()
        assert link.recv(0.2) is None
    finally:
        stop.set()
        t.join(2)
    link.unshare()
    assert not link.shared
