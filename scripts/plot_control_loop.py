#!/usr/bin/env python3
"""Draws a closed-loop run on tagdeflect's control output as one PNG: the achieved
net-deflection rate over 1 s windows against the target and its ±10 % band, the load, and the
control output's `valid` register, on one time axis. The first crack (the load's peak) and the
time the register was invalid are shaded in every panel.

Usage: plot_control_loop.py WINDOWS.csv SETS.csv --target MM_PER_MIN --out PNG

WINDOWS.csv: t_s,rate_mm_per_min,load_kN,valid (one row per 1 s window, t_s its middle).
SETS.csv:    t_s,valid,load_kN,stroke_mm,net_mm (one row per frame set: the register's valid
             after the set, the machine's load, stroke and true net deflection).
Both files are written by the closed-loop test (tests/it/control.rs) into target/.
Exits 2 with one line naming the file and line when an input is malformed.
"""

import argparse
import csv
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def read(path, columns):
    rows = []
    try:
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            missing = [c for c in columns if c not in (reader.fieldnames or [])]
            if missing:
                raise ValueError(f"{path}:1: missing column(s) {', '.join(missing)}")
            for n, r in enumerate(reader, start=2):
                try:
                    rows.append({c: float(r[c]) for c in columns})
                except (TypeError, ValueError):
                    raise ValueError(f"{path}:{n}: not a number in {r}") from None
    except OSError as e:
        raise ValueError(f"{path}: {e.strerror}") from None
    if len(rows) < 2:
        raise ValueError(f"{path}: {len(rows)} data row(s), need at least 2")
    return rows


def spans(ts, flags):
    """(start, end) of each run of true flags, ends at the next row's time."""
    out, start = [], None
    for i, (t, f) in enumerate(zip(ts, flags)):
        if f and start is None:
            start = t
        if not f and start is not None:
            out.append((start, t))
            start = None
    if start is not None:
        out.append((start, ts[-1]))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("windows")
    ap.add_argument("sets")
    ap.add_argument("--target", type=float, required=True, help="target net-deflection rate, mm/min")
    ap.add_argument("--out", required=True, help="PNG to write")
    a = ap.parse_args()
    try:
        win = read(a.windows, ["t_s", "rate_mm_per_min", "load_kN", "valid"])
        sets = read(a.sets, ["t_s", "valid", "load_kN", "stroke_mm", "net_mm"])
    except ValueError as e:
        print(f"plot_control_loop: {e}", file=sys.stderr)
        return 2

    ts = [r["t_s"] for r in sets]
    invalid = spans(ts, [r["valid"] == 0 for r in sets])
    peak = max(sets, key=lambda r: r["load_kN"])

    fig, (ax_rate, ax_load, ax_valid) = plt.subplots(
        3, 1, sharex=True, figsize=(9, 6.5), gridspec_kw={"height_ratios": [3, 2, 1]}
    )
    for ax in (ax_rate, ax_load, ax_valid):
        for s, e in invalid:
            ax.axvspan(s, e, color="#f4c7c3", lw=0)
        ax.axvline(peak["t_s"], color="#888888", ls="--", lw=1)
        ax.grid(True, color="#e6e6e6")

    ax_rate.axhspan(0.9 * a.target, 1.1 * a.target, color="#d9ead3", lw=0, label="target ±10 %")
    ax_rate.axhline(a.target, color="#38761d", lw=1)
    ax_rate.plot([r["t_s"] for r in win], [r["rate_mm_per_min"] for r in win], "o-", ms=3, color="#1c4587",
                 label="achieved rate (1 s windows)")
    ax_rate.set_ylabel("net deflection rate\nmm/min")
    ax_rate.legend(loc="lower left", fontsize=8)
    ax_rate.set_title("PI controller on the control output: constant net-deflection rate through a first crack", fontsize=10)

    ax_load.plot(ts, [r["load_kN"] for r in sets], color="#990000", lw=1.5)
    ax_load.set_ylabel("load, kN")
    ax_load.annotate("first crack", (peak["t_s"], peak["load_kN"]), xytext=(6, -12), textcoords="offset points", fontsize=8)

    ax_valid.step(ts, [r["valid"] for r in sets], where="post", color="#000000", lw=1.2)
    ax_valid.set_ylim(-0.2, 1.2)
    ax_valid.set_yticks([0, 1])
    ax_valid.set_ylabel("valid")
    ax_valid.set_xlabel("time since the actuator first moved, s  (shaded: register invalid, camera lost)")
    fig.tight_layout()
    fig.savefig(a.out, dpi=100)
    return 0


if __name__ == "__main__":
    sys.exit(main())
