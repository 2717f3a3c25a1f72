#!/usr/bin/env python3
"""A long synthetic feed for measuring the report's memory (docs/performance.md): LINES lines
of a three-camera rig (9 tags with sigma, 3 cameras, 2 gauges) at 30 sets/s, a beam loaded to
its peak and softening to 3.2 mm net deflection (ASTM C1609 with config/three-camera.toml).

With --varied the lines are less regular, for checking that the report's numbers do not change
with the way the feed is held: every sigma varies from line to line, tag 8 is missing from
every 7th line and tag 2's sigma from every 11th, every 13th line has no load, a UTM outage of
2 s, a clock check every 30 lines, a `cmod` gauge (EN 14651 with a notch) whose sigma is missing
on every 17th line, a camera without a frame on every 50th line and a `test` on every line.

usage: long_feed.py [--varied] LINES OUT.jsonl
"""
import json
import math
import sys

args = sys.argv[1:]
varied = "--varied" in args
args = [a for a in args if a != "--varied"]
lines, out = int(args[0]), args[1]
t0 = 1_780_000_000_000_000_000


def wobble(seq, k):
    """A deterministic relative variation of about ±20 %."""
    return 1.0 + 0.2 * math.sin(0.37 * seq + 1.3 * k)


with open(out, "w") as f:
    for seq in range(lines):
        d = 3.2 * seq / (lines - 1)  # net deflection, mm
        p = 45.0 * d / 0.06 if d < 0.06 else 15.0 + 30.0 * math.exp(-(d - 0.06) / 0.4)
        tags = []
        for i in range(9):
            if varied and i == 8 and seq % 7 == 3:
                continue
            s = [0.004, 0.004, 0.002]
            if varied:
                s = [round(v * wobble(seq, 3 * i + k), 7) for k, v in enumerate(s)]
            tag = {
                "id": i,
                "pos_mm": [60.0 * i, 0.0, 1500.0],
                "disp_mm": [0.0, 0.0, -d if i == 1 else 0.0],
                "views": 2 if not varied else 1 + (seq + i) % 3,
                "sigma_mm": s,
                "reproj_px": 0.12,
            }
            if varied:
                tag["disp_mm"] = [round(1e-4 * math.sin(seq + i), 7), round(-2e-4 * math.cos(seq), 7), -d if i == 1 else 0.0]
            if varied and i == 2 and seq % 11 == 5:
                del tag["sigma_mm"]
            tags.append(tag)
        cams = [
            {"name": n, "frame": True, "background_tags": 4, "specimen_tags": 6, "pose_reproj_px": 0.2, "posed": True,
             "drift_deg": 0.0, "drift_mm": 0.0, "pose_age_sets": 0, "dropped_frames": 0}
            for n in ("cam0", "cam1", "cam2")
        ]
        line = {
            "seq": seq,
            "t_ns": t0 + seq * 33_333_333,
            "load_kN": round(p, 4),
            "stroke_mm": round(1.3 * d, 5),
            "tags": tags,
            "net_deflection_mm": round(d, 5),
            "net_deflection_sigma_mm": 0.003,
            "reproj_px": 0.15,
            "cameras": cams,
            "utm": "ok",
            "dropped_sets": 0,
            "latency_ms": 40.0,
            "gauges": {"net_deflection": {"value": round(d, 5), "sigma": 0.003, "unit": "mm"},
                       "rotation": {"value": round(0.01 * d, 6), "sigma": 0.001, "unit": "mrad"}},
            "recording": "ok",
        }
        if varied:
            line["load_kN"] = round(p + 0.02 * math.sin(1.7 * seq), 4)
            if seq % 13 == 6:
                del line["load_kN"]
            if lines // 2 <= seq < lines // 2 + 60:
                line["utm"] = "down"
            if seq % 30 == 0:
                line["clock_offset_ms"] = {"value": round(3.0 + 0.001 * seq % 1.0, 3), "sigma": 0.4}
            cmod = {"value": round(0.8 * d, 5), "sigma": round(0.002 * wobble(seq, 40), 7), "unit": "mm"}
            if seq % 17 == 2:
                del cmod["sigma"]
            line["gauges"]["cmod"] = cmod
            line["gauges"]["rotation"]["sigma"] = round(0.001 * wobble(seq, 41), 7)
            if seq % 50 == 10:
                cams[1]["frame"] = False
            line["dropped_sets"] = seq // 1000
            line["test"] = {"id": "20261206T160000Z-B12", "specimen": "B12"}
        f.write(json.dumps(line, separators=(",", ":")) + "\n")
