#!/usr/bin/env python3
"""A long synthetic feed for measuring the report's memory (docs/performance.md): LINES lines
of a three-camera rig (9 tags with sigma, 3 cameras, 2 gauges) at 30 sets/s, a beam loaded to
its peak and softening to 3.2 mm net deflection (ASTM C1609 with config/three-camera.toml).

usage: long_feed.py LINES OUT.jsonl
"""
import json
import math
import sys

lines, out = int(sys.argv[1]), sys.argv[2]
t0 = 1_780_000_000_000_000_000
with open(out, "w") as f:
    for seq in range(lines):
        d = 3.2 * seq / (lines - 1)  # net deflection, mm
        p = 45.0 * d / 0.06 if d < 0.06 else 15.0 + 30.0 * math.exp(-(d - 0.06) / 0.4)
        tags = [
            {
                "id": i,
                "pos_mm": [60.0 * i, 0.0, 1500.0],
                "disp_mm": [0.0, 0.0, -d if i == 1 else 0.0],
                "views": 2,
                "sigma_mm": [0.004, 0.004, 0.002],
                "reproj_px": 0.12,
            }
            for i in range(9)
        ]
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
        f.write(json.dumps(line, separators=(",", ":")) + "\n")
