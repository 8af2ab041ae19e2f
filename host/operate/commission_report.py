"""The report page of ``upright commission`` (``DIR/report.html``): one self-contained HTML file.

Sections: the identified parameters against the nominal robot file with their 95 % intervals
(a plot of estimate / nominal with the interval as error bars, and a table), the final design
and its margins over the identification's confidence box (worst value / limit per scenario and
constraint), the verification on the robot (the 20 cm step and the 0.2 N push: x and phi as
the host read them, the verdicts), the balancing excitation's amplitude trials, and the time
each stage took.  Plots are PNG images embedded as base64 (matplotlib, Agg).
"""

from __future__ import annotations

import base64
import html
import io
import math
from pathlib import Path
from typing import Any, Mapping

__all__ = ["write_report"]


def _png(fig: Any) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return f'<img alt="plot" src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def _params_plot(ident: Mapping[str, Any]) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    e, ci, nom = ident["estimates"], ident.get("ci", {}), ident["nominal"]
    names = [k for k in ("I", "mL", "b", "kt", "ke", "pot_gain") if k in e and nom.get(k)]
    fig, ax = plt.subplots(figsize=(6, 3))
    for i, k in enumerate(names):
        r = e[k] / nom[k]
        lo, hi = (c / nom[k] for c in ci.get(k, [e[k], e[k]]))
        ax.errorbar([i], [r], yerr=[[max(0.0, r - lo)], [max(0.0, hi - r)]], fmt="o", capsize=4)
    ax.axhline(1.0, color="grey", lw=0.8)
    ax.set_xticks(range(len(names)), names)
    ax.set_ylabel("identified / nominal")
    ax.set_title("identified parameters, 95 % intervals")
    return _png(fig)


def _trace_plot(path: Path, title: str) -> str:
    import csv

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    head = rows[0]
    data = np.array([[float(v) for v in r] for r in rows[1:]])
    col = {h: data[:, i] for i, h in enumerate(head)}
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(6, 4), sharex=True)
    a1.plot(col["t"], col["x"], label="x (read)")
    a1.plot(col["t"], col["x_ref"], "--", label="reference")
    a1.set_ylabel("x (m)")
    a1.legend(fontsize=7)
    a2.plot(col["t"], col["phi"])
    a2.set_ylabel("phi (rad)")
    a2.set_xlabel("t (s)")
    a1.set_title(title)
    return _png(fig)


def _table(rows: list[dict[str, Any]], cols: list[str]) -> str:
    def cell(v: Any) -> str:
        if isinstance(v, float):
            return "inf" if math.isinf(v) else f"{v:.4g}"
        return html.escape(str(v))

    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)
    body = "".join("<tr>" + "".join(f"<td>{cell(r.get(c, ''))}</td>" for c in cols) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def write_report(out: Path, data: Mapping[str, Any]) -> Path:
    """Write ``out/report.html`` from the commissioning state's data; returns the path."""
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>upright commission</title>",
             "<style>body{font-family:sans-serif;max-width:60em;margin:auto}table{border-collapse:collapse}"
             "td,th{border:1px solid #ccc;padding:2px 6px;font-size:90%}</style></head><body>",
             "<h1>upright commission</h1>"]
    ident = data.get("identify")
    if ident:
        e, ci, nom = ident["estimates"], ident.get("ci", {}), ident["nominal"]
        parts += ["<h2>Identified robot</h2>", _params_plot(ident),
                  _table([{"parameter": k, "nominal": nom.get(k, math.nan), "identified": v,
                           "95 % low": ci.get(k, [math.nan, math.nan])[0], "95 % high": ci.get(k, [math.nan, math.nan])[1]}
                          for k, v in e.items()], ["parameter", "nominal", "identified", "95 % low", "95 % high"])]
        parts += [f"<p>{html.escape(n)}</p>" for n in ident.get("notes", [])]
    d2 = data.get("design2")
    if d2:
        parts += ["<h2>Design and margins</h2>",
                  f"<p>{html.escape(d2['name'])}: Q {d2['Q']}, R {d2['R']:g}, observer {d2['observer']:g}, "
                  f"force clamp {d2['u_max']:.3g} N, ki {d2['ki']:g} N/(m s); force row {d2['force_lsb']:.1f} LSB. "
                  f"Worst value/limit over the confidence box {d2['worst_ratio']:.3f}: margin "
                  f"{100 * d2['margin']:.0f} %.</p>",
                  *([f"<p>The robot failed the model's first choice, {html.escape(d2['chosen_by_model'])}, in "
                     "its verification: this runner-up of the same scoring is in force (the worst cases below "
                     "are the scoring's, in the table of candidates).</p>"] if d2.get("chosen_by_model") else []),
                  _table(d2.get("rows", []), ["scenario", "constraint", "worst", "limit", "ratio", "verdict", "fails",
                                              "points", "at"]),
                  "<p>Candidates scored:</p>", _table(d2.get("tried", []), ["name", "worst_ratio", "worst_ratio_push",
                                                                          "falls", "failing", "force_lsb", "error"])]
    ver = data.get("verify")
    if ver:
        parts.append("<h2>Verification on the robot</h2>")
        parts.append(_table([{"run": k, **v} for k, v in ver.items()],
                            ["run", "peak_phi", "peak_xddot", "settle", "fell", "pass", "skipped"]))
        if len(data.get("verify_tries", [])) > 1:
            parts += ["<p>Designs verified on the robot, in order:</p>",
                      _table(data["verify_tries"], ["name", "measured_ok"])]
        for k in ver:
            p = out / f"verify_{k}.csv"
            if p.exists():
                parts.append(_trace_plot(p, k))
    bal = data.get("balance")
    if bal:
        parts += ["<h2>Balancing excitation</h2>", _table(bal.get("tries", []), ["amplitude_n", "peak_phi", "stopped", "fell"]),
                  f"<p>identification run at {bal['amplitude_n']:.3g} N</p>"]
    tm = data.get("timing")
    if tm:
        parts += ["<h2>Stages</h2>", _table([{"stage": k, "seconds": v} for k, v in tm.items()], ["stage", "seconds"])]
    parts.append("</body></html>")
    path = Path(out) / "report.html"
    path.write_text("\n".join(parts))
    return path
