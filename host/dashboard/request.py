"""What a request to the dashboard must look like: its body's length, its JSON, each field's type and range.

Every check raises :class:`BadRequest` with the HTTP status and one line naming what is wrong
(the field, the header), which the server answers as ``{"error": "..."}``:

* ``Content-Length`` -- required on every ``POST`` (411; ``Transfer-Encoding`` is refused the
  same way), a non-negative decimal number (400), at most :data:`MAX_BODY` bytes (413); the
  body must arrive whole within :data:`REQUEST_TIMEOUT_S` (400 for a short body);
* the body -- empty, or one JSON object (400): no ``NaN``/``Infinity`` literals, no repeated
  key, no key the route does not know;
* each field -- its JSON type (a number is an ``int`` or ``float``, never ``true``), finite,
  and within the range the board could ever accept (:data:`REF_MAX_M`: the largest
  ``ref_limit_um`` of the parameter table), so nothing absurd reaches the link's encoder.
"""

from __future__ import annotations

import json
import math
import re
import socket
import time
from typing import Any, BinaryIO, Mapping

from firmware import msgtable as T

__all__ = ["BadRequest", "MAX_BODY", "REQUEST_TIMEOUT_S", "HEAD_TIMEOUT_S", "REF_MAX_M", "SQUARE_PERIOD_S",
           "content_length", "read_body", "json_args", "ROUTES"]

MAX_BODY = 256 * 1024
"""Largest request body (a gains module is ~10 kB; a page's ping a few kB)."""
REQUEST_TIMEOUT_S = 5.0
"""Idle read timeout of a connection, and the most time a request's body may take to arrive."""
HEAD_TIMEOUT_S = 10.0
"""The most time a request line and its headers may take, however slowly they trickle in."""
REF_MAX_M = max(p[4] for p in T.PARAMS if p[1] == "ref_limit_um") * 1e-6
"""The largest reference any board accepts (m): the top of ``ref_limit_um``'s range; the board
refuses beyond its own (smaller) limit."""
SQUARE_PERIOD_S = (0.2, 60.0)
"""Range of the square wave's period (s)."""
_LIST_MAX = 10000


class BadRequest(ValueError):
    """A request refused before it reaches the board: ``status`` and a one-line ``text``."""

    def __init__(self, status: int, text: str) -> None:
        super().__init__(text)
        self.status = status
        self.text = text


def content_length(headers: Mapping[str, str] | Any) -> int:
    """The body length a ``POST`` declares.

    Raises
    ------
    BadRequest
        411 without ``Content-Length`` or with ``Transfer-Encoding``; 400 for a value that is not a
        non-negative decimal number (or two different values); 413 beyond :data:`MAX_BODY`.
    """
    if headers.get("Transfer-Encoding") is not None:
        raise BadRequest(411, "Transfer-Encoding is not accepted: send the body with a Content-Length")
    values = headers.get_all("Content-Length") if hasattr(headers, "get_all") else [headers.get("Content-Length")]
    values = [v for v in (values or []) if v is not None]
    if not values:
        raise BadRequest(411, "Content-Length required (0 for no body)")
    if len({v.strip() for v in values}) > 1:
        raise BadRequest(400, f"Content-Length given twice with different values: {', '.join(values)}")
    raw = values[0].strip()
    if raw.startswith("-") and raw[1:].isdigit():
        raise BadRequest(400, f"Content-Length {raw} is negative")
    if not re.fullmatch(r"[0-9]{1,20}", raw):
        raise BadRequest(400, f"Content-Length {raw[:40]!r} is not a number of bytes")
    n = int(raw)
    if n > MAX_BODY:
        raise BadRequest(413, f"request body of {n} bytes is too large (at most {MAX_BODY})")
    return n


def read_body(rfile: BinaryIO, sock: socket.socket, n: int, timeout: float = REQUEST_TIMEOUT_S) -> bytes:
    """Read exactly ``n`` bytes of body within ``timeout`` seconds in all (the socket's timeout is
    set to what is left before each read, and restored).

    Raises
    ------
    BadRequest
        400 when the connection closes or the time runs out before ``n`` bytes came.
    """
    if n == 0:
        return b""
    deadline = time.monotonic() + timeout
    chunks: list[bytes] = []
    got = 0
    old = sock.gettimeout()
    try:
        while got < n:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError
            sock.settimeout(left)
            chunk = rfile.read1(n - got)  # type: ignore[attr-defined]
            if not chunk:
                raise BadRequest(400, f"request body shorter than its Content-Length: {got} of {n} bytes "
                                      "before the connection closed")
            chunks.append(chunk)
            got += len(chunk)
    except TimeoutError:
        raise BadRequest(400, f"request body shorter than its Content-Length: {got} of {n} bytes "
                              f"in {timeout:g} s") from None
    finally:
        try:
            sock.settimeout(old)
        except OSError:
            pass
    return b"".join(chunks)


# ---------------------------------------------------------------- JSON and fields
def _no_constant(name: str) -> Any:
    raise BadRequest(400, f"body is not JSON: {name} is not a JSON number")


def _no_repeats(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in pairs:
        if k in out:
            raise BadRequest(400, f"key {k!r} given twice")
        out[k] = v
    return out


def _number(key: str, v: Any, lo: float, hi: float, unit: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise BadRequest(400, f"{key} must be a number, got {type(v).__name__} {_short(v)}")
    if isinstance(v, int) and abs(v) > 10**15:  # float(v) of a huge int would overflow
        raise BadRequest(400, f"{key} = {_short(v)} {unit} is out of range ({lo:g}..{hi:g} {unit})".rstrip())
    x = float(v)
    if not math.isfinite(x):
        raise BadRequest(400, f"{key} must be finite, got {v!r}")
    if not lo <= x <= hi:
        raise BadRequest(400, f"{key} = {x:g} {unit} is out of range ({lo:g}..{hi:g} {unit})")
    return x


def _short(v: Any) -> str:
    s = repr(v)
    return s if len(s) <= 40 else s[:37] + "..."


def _samples(key: str, v: Any) -> list[float]:
    # a page's measurements: numbers, or null (JSON.stringify's NaN), at most _LIST_MAX of them
    if not isinstance(v, list):
        raise BadRequest(400, f"{key} must be a list of numbers, got {type(v).__name__}")
    if len(v) > _LIST_MAX:
        raise BadRequest(400, f"{key}: {len(v)} samples (at most {_LIST_MAX})")
    out = []
    for i, e in enumerate(v):
        if e is None:
            continue
        if isinstance(e, bool) or not isinstance(e, (int, float)):
            raise BadRequest(400, f"{key}[{i}] must be a number, got {type(e).__name__} {_short(e)}")
        if isinstance(e, float) and not math.isfinite(e):
            continue
        if isinstance(e, int) and abs(e) > 10**15:
            raise BadRequest(400, f"{key}[{i}] = {_short(e)} is out of range")
        out.append(float(e))
    return out


def _flag(key: str, v: Any) -> bool:
    if not isinstance(v, bool):
        raise BadRequest(400, f"{key} must be true or false, got {type(v).__name__} {_short(v)}")
    return v


_REF = ("m", -REF_MAX_M, REF_MAX_M)
#: route -> {key: kind}; kinds: ("num", unit, lo, hi), "samples", "flag"
ROUTES: dict[str, dict[str, Any]] = {
    "/api/ping": {"latency_ms": "samples", "updates": "samples"},
    "/api/arm": {}, "/api/disarm": {}, "/api/clear": {}, "/api/upright": {},
    "/api/record/start": {}, "/api/record/stop": {},
    "/api/reference": {"x": ("num", *_REF)},
    "/api/square": {"amplitude": ("num", "m", -2 * REF_MAX_M, 2 * REF_MAX_M),
                    "period": ("num", "s", *SQUARE_PERIOD_S), "low": ("num", *_REF), "stop": "flag"},
}
_REQUIRED = {"/api/reference": ("x",)}


def json_args(route: str, body: bytes) -> dict[str, Any]:
    """The body of a JSON route as checked values (``{}`` for an empty body).

    Raises
    ------
    BadRequest
        400: not UTF-8 JSON, not an object, a repeated, unknown or missing key, a value of the
        wrong type, not finite or out of range.
    """
    spec = ROUTES[route]
    if not body.strip():
        obj: Any = {}
    else:
        try:
            obj = json.loads(body.decode("utf-8"), parse_constant=_no_constant, object_pairs_hook=_no_repeats)
        except BadRequest:
            raise
        except UnicodeDecodeError:
            raise BadRequest(400, "body is not UTF-8 text") from None
        except RecursionError:
            raise BadRequest(400, "body is not JSON: nested too deeply") from None
        except json.JSONDecodeError as exc:
            raise BadRequest(400, f"body is not JSON: {exc.msg} (line {exc.lineno}, column {exc.colno})") from None
        except ValueError as exc:  # e.g. an integer of more than 4300 digits
            raise BadRequest(400, f"body is not JSON: {' '.join(str(exc).split())[:120]}") from None
    if not isinstance(obj, dict):
        raise BadRequest(400, f"the body must be a JSON object, got {type(obj).__name__}")
    unknown = [k for k in obj if k not in spec]
    if unknown:
        known = ", ".join(spec) or "none"
        raise BadRequest(400, f"unknown key {unknown[0]!r} for {route} (known: {known})")
    for k in _REQUIRED.get(route, ()):
        if k not in obj:
            raise BadRequest(400, f"missing key {k!r} for {route}")
    out: dict[str, Any] = {}
    for k, v in obj.items():
        kind = spec[k]
        if kind == "samples":
            out[k] = _samples(k, v)
        elif kind == "flag":
            out[k] = _flag(k, v)
        else:
            _, unit, lo, hi = kind
            out[k] = _number(k, v, lo, hi, unit)
    if route == "/api/square" and not out.get("stop"):
        top = out.get("low", 0.0) + out.get("amplitude", 0.2)
        if abs(top) > REF_MAX_M:
            raise BadRequest(400, f"low + amplitude = {top:g} m is out of range "
                                  f"({-REF_MAX_M:g}..{REF_MAX_M:g} m)")
    return out
