"""The port hub on a deep ``$TMPDIR`` (issue 22 item 3's hub; a CI failure of stop 43).

A Unix socket's address holds at most 107 bytes.  Under pytest-xdist a test's ``$TMPDIR``
(``/tmp/pytest-of-root/pytest-106/popen-gw0/test_readme_usb_link_commands0``) made the hub's
socket path longer than that: the bind failed, the owner went on without a hub (a second tool
would have been refused "port busy") and left its private directory behind.  Here a real pty
is the port, two :class:`host.link.clients.SerialLink` share it through the hub on a path well
past the limit, and nothing is left behind.
"""

from __future__ import annotations

import os
import select
import tempfile
from pathlib import Path

import pytest

from host.link import messages as M
from host.link import porthub
from host.link.clients import SerialLink


@pytest.fixture
def deep_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    deep = tmp_path / ("d" * 60) / ("e" * 60)
    deep.mkdir(parents=True)
    monkeypatch.setattr(tempfile, "tempdir", str(deep))
    return deep


def _read_frames(fd: int, want: int, wall: float = 5.0) -> list[M.Message]:
    dec = M.SerialStreamDecoder()
    got: list[M.Message] = []
    while len(got) < want and select.select([fd], [], [], wall)[0]:
        got += [m for m, _ in dec.feed(os.read(fd, 4096))]
    return got


def test_a_second_tool_shares_the_port_through_a_hub_on_a_long_path(deep_tmp: Path) -> None:
    master, slave = os.openpty()
    port = os.ttyname(slave)
    try:
        owner = SerialLink(port)
        path = porthub.hub_path(port, create=False)
        assert path is not None and len(os.fsencode(str(path))) > porthub.SUN_PATH_MAX
        assert owner._hub is not None and path.exists(), "the owner serves no hub"
        tool = SerialLink(port)
        try:
            assert tool.via_hub, "the second tool did not attach to the owner's hub"
            tool.send(M.BY_NAME["set_reference"](x_um=1234))
            got = _read_frames(master, 1)
            assert [m.NAME for m in got] == ["set_reference"] and got[0].x_um == 1234, got
        finally:
            tool.close()
        owner.close()
    finally:
        os.close(master)
        os.close(slave)
    assert list(deep_tmp.iterdir()) == [], "the hub left its directory behind"


def test_a_hub_that_cannot_bind_leaves_no_directory(deep_tmp: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(call, path):  # noqa: ANN001 - the signature of porthub._sock_call
        raise OSError(36, "File name too long")

    monkeypatch.setattr(porthub, "_sock_call", refuse)
    master, slave = os.openpty()
    try:
        owner = SerialLink(os.ttyname(slave))
        assert owner._hub is None  # the port stays exclusive without a hub
        owner.close()
    finally:
        os.close(master)
        os.close(slave)
    assert list(deep_tmp.iterdir()) == [], "the failed hub left its directory behind"
