"""One of each on the host (issue 25 item 3): one fault table, one keepalive, one loss counter.

The fault names of the CLI, ``upright board status`` and the dashboard are the protocol table's
(``msgtable.FAULTS``); every tool that keeps a board armed sends its host heartbeat through
:class:`host.link.clients.Keepalive`; HIL runs, the board recorder and the dashboard count lost
frames with :class:`host.hil.accounting.SeqAccount`.
"""

from __future__ import annotations

from pathlib import Path

from firmware import msgtable as T
from host.dashboard.hub import Hub
from host.hil.accounting import SeqAccount
from host.link import messages as M
from host.link.clients import Keepalive, Link
from host.operate.board import fault_names, fault_table
from host.operate.record import Recorder

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
