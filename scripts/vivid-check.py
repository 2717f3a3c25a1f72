#!/usr/bin/env python3
"""Checks what scripts/vivid-vm.sh brought back from the VM and prints PASS/FAIL per check.

    scripts/vivid-check.py OUT_DIR CYCLES

OUT_DIR holds: events (name epoch_ns [extra]), samples (name epoch_ns key=value...),
daemon.log (the daemon's stderr), feed.jsonl, rec/ (the recording: frames.jsonl, vivid/*.pgm),
console.log. Exit status 1 when a check fails.
"""
import json
import os
import re
import sys


def read_lines(path):
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            return f.read().splitlines()
    except FileNotFoundError:
        return []


def read_pgm(path):
    with open(path, "rb") as f:
        data = f.read()
    # P5 <w> <h> <max>\n<bytes>
    m = re.match(rb"P5\s+(\d+)\s+(\d+)\s+(\d+)\s", data)
    if not m:
        raise ValueError(f"{path}: not a binary PGM")
    w, h = int(m.group(1)), int(m.group(2))
    return w, h, data[m.end():m.end() + w * h]


def main():
    out, cycles = sys.argv[1], int(sys.argv[2])
    results = []

    def check(name, ok, figures):
        results.append(ok)
        print(f"{'PASS' if ok else 'FAIL'}  {name}: {figures}")

    events = []
    for line in read_lines(os.path.join(out, "events")):
        parts = line.split(" ", 2)
        events.append((parts[0], int(parts[1]), parts[2] if len(parts) > 2 else ""))
    samples = {}
    for line in read_lines(os.path.join(out, "samples")):
        parts = line.split()
        samples[parts[0]] = {k: int(v) for k, v in (p.split("=") for p in parts[2:])}
        samples[parts[0]]["t"] = int(parts[1])
    log = read_lines(os.path.join(out, "daemon.log"))
    frames = [json.loads(l) for l in read_lines(os.path.join(out, "rec", "frames.jsonl")) if l.strip()]
    feed = [json.loads(l) for l in read_lines(os.path.join(out, "feed.jsonl")) if l.strip()]

    def times(name):
        return [t for (n, t, _) in events if n == name]

    unplugs, replugs, reopened = times("unplug"), times("replug"), times("reopened")
    exited = [x for (n, _, x) in events if n == "exited"]
    info = " ".join(read_lines(os.path.join(out, "v4l2-info")))
    driver = re.search(r"Driver name\s*:\s*(\S+)", info)
    print(f"device: {driver.group(1) if driver else '?'} /dev/video0, "
          f"{len(unplugs)} unplugs (unbind), {len(replugs)} replugs (bind); "
          f"{len(frames)} frames recorded, {len(feed)} feed lines")

    # 1. The daemon survived and stopped cleanly on SIGTERM.
    stopped = any("SIGTERM: stopping" in l for l in log)
    panicked = [l for l in log if "panicked" in l]
    check("daemon survived, exit 0 on SIGTERM", exited == ["code=0"] and stopped and not panicked and "no-exit" not in [e[0] for e in events],
          f"exit {exited[0] if exited else 'none'}, 'SIGTERM: stopping' logged: {stopped}, panics: {len(panicked)}")

    # 2. Loss and reopening logged, once per cycle.
    lost_lines = [l for l in log if "camera lost" in l and "reopening" in l]
    reopen_lines = [l for l in log if "camera reopened" in l]
    released = [l for l in log if "releasing its buffers" in l]
    reasons = sorted({re.sub(r".*camera lost: ", "", l).replace("; reopening", "") for l in lost_lines})
    check("loss logged per unplug", len(lost_lines) == cycles and len(unplugs) == cycles,
          f"{len(lost_lines)} 'camera lost' for {len(unplugs)} unplugs; reason(s): {reasons}; "
          f"'STREAMOFF: device gone; releasing' lines: {len(released)}")
    check("reopen logged per replug", len(reopen_lines) == cycles and len(reopened) == cycles,
          f"{len(reopen_lines)} 'camera reopened' for {len(replugs)} replugs")

    # 3. Frames before the first unplug and after every replug (recording and feed).
    def frames_between(a, b):
        return [f for f in frames if a <= f["t_ns"] < b]

    def feed_between(a, b):
        return [l for l in feed if a <= l["t_ns"] < b and any(c.get("frame") for c in l.get("cameras", []))]

    end = times("sigterm")[0] if times("sigterm") else 2**63 - 1
    before = frames_between(0, unplugs[0]) if unplugs else frames
    feed_before = feed_between(0, unplugs[0]) if unplugs else feed
    after, feed_after, reopen_s, first_frame_s = [], [], [], []
    for i, r in enumerate(replugs):
        nxt = unplugs[i + 1] if i + 1 < len(unplugs) else end
        fb = frames_between(r, nxt)
        after.append(len(fb))
        feed_after.append(len(feed_between(r, nxt)))
        if i < len(reopened):
            reopen_s.append((reopened[i] - r) / 1e9)
        if fb:
            first_frame_s.append((fb[0]["t_ns"] - r) / 1e9)
    away = [len(frames_between(u, replugs[i])) for i, u in enumerate(unplugs) if i < len(replugs)]
    seqs = [f["seq"] for f in frames]
    check("frames before the first unplug and after every replug",
          len(before) >= 10 and len(after) == cycles and all(n >= 10 for n in after) and len(feed_before) >= 10 and all(n >= 10 for n in feed_after),
          f"recorded frames before {len(before)}, after each replug {after}, while away {away}; "
          f"feed lines with a frame before {len(feed_before)}, after {feed_after}")
    # `seq` goes on across reopenings (never back, never repeated); a gap is a frame the daemon
    # counted as dropped — by the recorder (a full queue on a busy machine: `recorder_dropped`
    # in its last line) or at the source (the feed's `dropped_frames`) — never one lost unsaid.
    rec_dropped = max([int(m) for l in log for m in re.findall(r"recorder_dropped=(\d+)", l)] or [0])
    src_dropped = max([c.get("dropped_frames", 0) for l in feed for c in l.get("cameras", [])] or [0])
    missing = (seqs[-1] + 1 - len(seqs)) if seqs else 0
    rising = all(b > a for a, b in zip(seqs, seqs[1:]))
    check("frame counter continues across reopenings",
          bool(seqs) and seqs[0] == 0 and rising and missing <= rec_dropped + src_dropped,
          f"seq 0..{seqs[-1] if seqs else '-'} over {len(seqs)} frames, rising: {rising}, {missing} missing; "
          f"the daemon counted {rec_dropped} dropped by the recorder, {src_dropped} at the source")
    fmt = lambda xs: "[" + ", ".join(f"{x:.2f}" for x in xs) + "]"
    check("camera back after each replug", len(reopen_s) == cycles and len(first_frame_s) == cycles,
          f"replug → 'camera reopened' {fmt(reopen_s)} s, replug → first frame {fmt(first_frame_s)} s (reopen backoff 0.5 s doubling to 10 s)")

    # 4. The recorded images are the driver's picture, before and after.
    def image_stats(f):
        w, h, px = read_pgm(os.path.join(out, "rec", f["file"]))
        mean = sum(px) / len(px)
        sd = (sum((p - mean) ** 2 for p in px[::7]) / len(px[::7])) ** 0.5
        return w, h, len(set(px)), sd

    try:
        picks = ([before[len(before) // 2]] if before else []) + [frames_between(r, unplugs[i + 1] if i + 1 < len(unplugs) else end)[-1]
                                                                for i, r in enumerate(replugs) if after[i]]
        st = [image_stats(f) for f in picks]
        ok = len(st) == cycles + 1 and all(w == 640 and h == 480 and levels >= 8 and sd > 10 for (w, h, levels, sd) in st)
        check("recorded images are the test pattern (not blank)", ok,
              "; ".join(f"{f['file']} {w}x{h} {levels} grey levels sd {sd:.0f}" for f, (w, h, levels, sd) in zip(picks, st)))
    except (OSError, ValueError, IndexError) as e:
        check("recorded images are the test pattern (not blank)", False, str(e))

    # 5. No fd/mapping leak: released while away, as many after each replug as before.
    b = samples.get("before", {})
    aw = [samples.get(f"away{c}", {}) for c in range(1, cycles + 1)]
    bk = [samples.get(f"back{c}", {}) for c in range(1, cycles + 1)]
    ok = bool(b) and b.get("video_fds", 0) >= 1 and b.get("video_maps", 0) >= 1 \
        and all(a.get("video_fds") == 0 and a.get("video_maps") == 0 for a in aw) \
        and all(k.get("video_fds") == b["video_fds"] and k.get("video_maps") == b["video_maps"] for k in bk) \
        and all(k.get("all_fds") == b["all_fds"] for k in bk)
    fig = lambda key: f"{b.get(key, '?')} → away {[a.get(key, '?') for a in aw]} → back {[k.get(key, '?') for k in bk]}"
    check("no fd or mmap leak", ok,
          f"/dev/video fds {fig('video_fds')}; /dev/video mappings {fig('video_maps')}; all fds {fig('all_fds')}; "
          f"all mappings {fig('all_maps')}")

    # 6. What the feed says without tags: a line per frame set, no tag, the camera's frame.
    if feed:
        first = feed[0]
        cam = first.get("cameras", [{}])[0]
        untagged = all(l.get("tags") == [] for l in feed)
        check("feed lines without tags carry the camera's frame", untagged and all(len(l.get("cameras", [])) == 1 for l in feed),
              f"every line has \"tags\": []: {untagged}; first line: {json.dumps(first, separators=(',', ':'))[:300]}")
        print(f"      camera health in the first line: frame={cam.get('frame')} posed={cam.get('posed')} "
              f"background_tags={cam.get('background_tags')} dropped_frames={cam.get('dropped_frames')}")
    else:
        check("feed lines without tags carry the camera's frame", False, "no feed lines")

    failed = results.count(False)
    print(f"{'PASS' if not failed else 'FAIL'}: {len(results) - failed}/{len(results)} checks passed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
