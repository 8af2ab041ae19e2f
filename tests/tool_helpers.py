"""What the tests of the board tools and the dashboard share: reading a tool's summary line and
asking the dashboard's HTTP API (imported by name: ``import tool_helpers as TH``)."""

from __future__ import annotations

import json
import urllib.error
import urllib.request


def log_summary(stderr: str) -> tuple[int, int, str]:
    """``upright board log``'s last summary line ``upright board: N rows (M telemetry frames) ...;
    K lost``: ``(N, M, line)``."""
    line = [s for s in stderr.splitlines() if "rows (" in s][-1]
    return int(line.split("upright board: ")[1].split()[0]), int(line.split("(")[1].split()[0]), line


def http_json(url: str, data: bytes | None = None, headers: dict | None = None,
              timeout: float = 10) -> tuple[int, dict]:
    """GET (or POST ``data``) ``url``: the status and the JSON body, also of an HTTP error."""
    r = urllib.request.Request(url, data=data, headers=headers or {}, method="POST" if data is not None else "GET")
    try:
        with urllib.request.urlopen(r, timeout=timeout) as res:
            return res.status, json.loads(res.read() or b"{}")
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read() or b"{}")
