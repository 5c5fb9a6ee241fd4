"""Reports of a set of configuration records: the paper's tables and figures, ours beside theirs."""

from __future__ import annotations

import json
import math
import os
import pathlib
from typing import Any

import numpy as np

from ._figures import DATA_TITLES, plot_figures
from ._paper import FIGURES, SEGMENTS, TABLES
from .protocol import METHOD_LABELS, METHODS


def _key(r: dict):
    return (r["example"], r["data"], r["method"], int(r["segments"]))


def load_records(path: pathlib.Path) -> list[dict]:
    """Records of `summary.json` in `path` (empty when absent).

    Raises a `ValueError` naming the file when it is not a JSON list of records, or when a
    record lacks a field the report needs (`REQUIRED_FIELDS`) or has one of the wrong kind;
    records of earlier versions, without the provenance fields, load as they are.
    """
    f = pathlib.Path(path) / "summary.json"
    if not f.exists():
        return []
    try:
        records: Any = _decode(json.loads(f.read_text()))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{f} is not valid JSON ({err})") from err
    if not (isinstance(records, list) and all(isinstance(r, dict) and _KEY_FIELDS <= set(r)
                                              for r in records)):
        raise ValueError(f"{f} is not a list of records (dicts with the fields "
                         f"{', '.join(sorted(_KEY_FIELDS))})")
    for i, r in enumerate(records):
        problem = _record_problem(r)
        if problem:
            raise ValueError(f"{f}: record {i} ({r['example']}, {r['data']}, {r['method']}, "
                             f"N={r['segments']}) {problem}")
    return records


def _record_problem(r: dict) -> str | None:
    """What keeps record `r` from a report (None if nothing)."""
    from .data import REGIMES
    from .protocol import EXAMPLES

    missing = [k for k in REQUIRED_FIELDS if k not in r]
    if missing:
        return f"lacks the fields {', '.join(missing)}"
    for field, allowed in (("example", EXAMPLES), ("data", REGIMES), ("method", METHODS)):
        if r[field] not in allowed:
            return f"has {field} {r[field]!r}, not one of {', '.join(allowed)}"
    if isinstance(r["segments"], bool) or not isinstance(r["segments"], int):
        return f"has segments {r['segments']!r}, not an integer"
    wrong = [k for k in _METRIC_FIELDS
             if isinstance(r[k], bool) or not isinstance(r[k], int | float)]
    if wrong:
        return f"has non-numeric {', '.join(wrong)}"
    return None


#: Non-finite numbers (the test MSE of an unstable loop is infinite) are written as these
#: strings, so that `summary.json` is strict JSON (no `Infinity` or `NaN` tokens).
_NON_FINITE = {"inf": float("inf"), "-inf": float("-inf"), "nan": float("nan")}


def _encode(obj):
    if isinstance(obj, float) and not np.isfinite(obj):
        return str(obj)
    if isinstance(obj, dict):
        return {k: _encode(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_encode(v) for v in obj]
    return obj


def write_json(path, obj) -> None:
    """Write `obj` to `path` as strict JSON, non-finite floats as the strings above.

    Written to a temporary file that then replaces `path`, so that an interrupted write
    (the command line saves `summary.json` after every configuration) leaves the previous
    file whole.
    """
    path = pathlib.Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(_encode(obj), indent=1, allow_nan=False))
    os.replace(tmp, path)


def _decode(obj):
    if isinstance(obj, str) and obj in _NON_FINITE:
        return _NON_FINITE[obj]
    if isinstance(obj, dict):
        return {k: _decode(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_decode(v) for v in obj]
    return obj


_KEY_FIELDS = {"example", "data", "method", "segments"}
_METRIC_FIELDS = ("percent_stable", "percent_change_cost", "train_time_s", "mse_q1",
                  "mse_median", "mse_q3", "mse_max")
#: The fields every record in `summary.json` must have: the tables and figures read them.
REQUIRED_FIELDS = ("example", "data", "method", "segments", *_METRIC_FIELDS)
#: Settings that must agree between the records of one example in a report: its tables
#: set results side by side and state one count of controllers per configuration.
SETTINGS = ("seed", "inits", "quick")
#: What produced a record that must also agree, where both records state it: records
#: written before these fields existed (0.1.0) are taken as they are.
PROVENANCE = ("dissil_jax_version", "dtype")


def _settings(r: dict) -> tuple:
    return tuple(r.get(k) for k in SETTINGS)


def _describe(r: dict) -> str:
    """`r`'s settings, and its provenance where recorded, as "seed 0, inits 2, ..."."""
    settings = [f"{k} {'unknown' if r.get(k) is None else r[k]}" for k in SETTINGS]
    return ", ".join(settings + [f"{k} {r[k]}" for k in PROVENANCE if r.get(k) is not None])


def _clash(a: dict, b: dict) -> bool:
    """Whether records `a` and `b` of one example cannot share a report."""
    return _settings(a) != _settings(b) or any(
        a.get(k) is not None and b.get(k) is not None and a[k] != b[k] for k in PROVENANCE)


def merge_records(old: list[dict], new: list[dict]) -> list[dict]:
    """New records replace old ones of the same (example, data, method, segments).

    The records of one example that remain must share their `seed`, `inits` and `quick`
    settings, and their `dissil_jax_version` and `dtype` where both records state them: a
    `ValueError` refuses to mix them in one report. Records written before those fields
    existed are kept beside new ones (their version is unknown).
    """
    merged = {_key(r): r for r in old}
    merged.update({_key(r): r for r in new})
    for r_new in new:
        for r in merged.values():
            if r["example"] == r_new["example"] and _clash(r, r_new):
                raise ValueError(
                    f"the {r['example']} records already in the report have "
                    f"{_describe(r)}, the new ones {_describe(r_new)}; "
                    "one report holds one setting per example")
    return sorted(merged.values(), key=lambda r: (r["example"], r["data"],
                                                  METHODS.index(r["method"]), r["segments"]))


def _fmt(x, kind: str) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "–"
    if isinstance(x, float) and math.isinf(x):
        return "∞"
    if kind == "pct":
        return f"{x:.0f}"
    if kind == "chg":
        return f"{x:.2f}"
    if kind == "time":
        return f"{x:.3g}"
    return f"{x:.3g}"


def tables_markdown(records: list[dict]) -> str:
    """The paper's Tables 2-5 layout, one table per (example, data) present in `records`.

    Each cell reads `ours (paper)`; the paper's numbers come from its LaTeX source. A
    second table per configuration gives the test-MSE statistics of Figures 1-6, with the
    paper's median read from its figure data.
    """
    out = ["# Results", "",
           "Each cell: **ours** (paper). Percent stable counts controllers whose closed loop "
           "is stable in testing; percent change in cost is the mean relative change of the "
           "training loss; training time is wall seconds per controller (ours: all "
           "initialisations of a configuration trained together, XLA compilation included, "
           "so a configuration that runs first in its process pays more). Test MSE: plant-state MSE against "
           "the expert from the same test states and noise; unstable controllers count as ∞. "
           "Certified: every controller of the configuration holds the float64 certificate "
           "(– for the unconstrained methods).", ""]
    groups = sorted({(r["example"], r["data"]) for r in records},
                    key=lambda k: (k[0] != "linear", k[1] != "initial"))
    for example, data in groups:
        rows = [r for r in records if r["example"] == example and r["data"] == data]
        segs = sorted({r["segments"] for r in rows})
        methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
        by = {(r["method"], r["segments"]): r for r in rows}
        paper = TABLES.get((example, data), {})
        pseg = SEGMENTS[example]
        out += [f"## {example.capitalize()} example — {DATA_TITLES[data].lower()}", "",
                _settings_line(rows), ""]
        if any(r.get("quick") for r in rows):
            out += ["**Quick run** (`--quick`): fewer plants, test states and training steps "
                    "than the paper's protocol, so the numbers are not comparable with the "
                    "paper's.", ""]
        counts = ", ".join(
            f"{METHOD_LABELS[m]} {r['controllers']} ({r['plants']} plant(s) × {r['inits']})"
            for m in methods for r in [next(r for r in rows if r["method"] == m)]
            if "controllers" in r)
        if counts:
            out += [f"Controllers per configuration: {counts}.", ""]
        # one table per quantity (the paper's tables set all three side by side)
        for name, field, idx, kind in (("% stable", "percent_stable", 0, "pct"),
                                       ("% change in cost", "percent_change_cost", 1, "chg"),
                                       ("training time (s per controller)", "train_time_s",
                                        2, "time")):
            out += [f"**{name}**", "", "| method | " + " | ".join(f"N={s}" for s in segs)
                    + " |", "|" + " --- |" * (1 + len(segs))]
            for m in methods:
                cells = []
                for s in segs:
                    r = by.get((m, s))
                    ours = _fmt(r[field], kind) if r else "–"
                    p = (paper[m][idx][pseg.index(s)]
                         if m in paper and s in pseg else None)
                    cells.append(f"**{ours}** ({_fmt(p, kind)})")
                out.append(f"| {METHOD_LABELS[m]} | " + " | ".join(cells) + " |")
            out.append("")
        out += [f"**Test MSE** ({example}, {DATA_TITLES[data].lower()}): median and worst "
                "controller (the paper's in parentheses), quartiles; % bounded (the weaker "
                "verdict, equal to % stable where the test is exact); test horizon "
                f"{_steps([t for r in rows for t in r.get('test_steps') or ()])} steps.", ""]
        out += ["| method | N | median | q1 | q3 | max | % bounded | certified |",
                "| --- | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
        pmed = dict(FIGURES.get((example, data, "median"), {}))
        pmax = dict(FIGURES.get((example, data, "max"), {}))
        for m in methods:
            for s in segs:
                r = by.get((m, s))
                if r is None:
                    continue
                pm = dict(pmed.get(m, ())).get(s)
                px = dict(pmax.get(m, ())).get(s)
                out.append(f"| {METHOD_LABELS[m]} | {s} | **{_fmt(r['mse_median'], 'g')}** "
                           f"({_fmt(pm, 'g')}) | {_fmt(r['mse_q1'], 'g')} | "
                           f"{_fmt(r['mse_q3'], 'g')} | **{_fmt(r['mse_max'], 'g')}** "
                           f"({_fmt(px, 'g')}) | {_fmt(r.get('percent_bounded'), 'pct')} | "
                           f"{certified_cell(r)} |")
        out.append("")
    return "\n".join(out)


def certified_cell(record: dict) -> str:
    """A record's `certified` for a table: all, not all, or – (a method without one)."""
    return {True: "all", False: "not all"}.get(record.get("certified"), "–")


def _settings_line(rows: list[dict]) -> str:
    """The settings and provenance of a section's records, as one sentence."""
    def values(key):
        return sorted({str(r[key]) for r in rows if r.get(key) is not None})

    parts = [f"{label} {', '.join(v)}" for label, key in (
        ("seed", "seed"), ("initialisations", "inits"), ("dissil_jax", "dissil_jax_version"),
        ("jax", "jax_version"), ("dtype", "dtype"), ("CPU count", "cpu_count"))
        for v in [values(key)] if v]
    commits = values("git_commit")
    if commits:
        parts.append("commit " + ", ".join(c[:10] + ("-dirty" if c.endswith("-dirty") else "")
                                          for c in commits))
    dates = values("date")
    if dates:
        parts.append(f"recorded {dates[0][:10]}" + (f" to {dates[-1][:10]}"
                                                     if dates[-1][:10] != dates[0][:10] else ""))
    missing = [label for label, key in (("versions", "dissil_jax_version"), ("dtype", "dtype"),
                                         ("CPU count", "cpu_count"), ("date", "date"))
               if not values(key)]
    if missing:  # records written before they stated their provenance
        parts.append(f"{', '.join(missing)} not recorded")
    return "Settings: " + "; ".join(parts) + "."


def _steps(steps) -> str:
    """The test horizon(s) of a record: one number, or the range over plants."""
    if not steps:
        return "–"
    lo, hi = min(steps), max(steps)
    return f"{lo}" if lo == hi else f"{lo}–{hi}"


def write_report(records: list[dict], out_dir) -> tuple[pathlib.Path, list[pathlib.Path]]:
    """Write `summary.json`, `tables.md` and the figures into `out_dir`."""
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "summary.json", records)
    tables = out_dir / "tables.md"
    tables.write_text(tables_markdown(records))
    return tables, plot_figures(records, out_dir)
