#!/usr/bin/env python3
"""The daemon's memory while it makes a long test's report at its stop, measured in a memory
cgroup as the unit's `MemoryMax` bounds it (docs/performance.md, "The daemon's report at a
test's stop, measured").

1. `tagdeflect demo --tests DIR` (the built-in simulated rig: three cameras, the simulated UTM
   over Modbus TCP) starts an ASTM C1609 test; once it has ~20 lines the daemon is killed
   (SIGKILL), leaving the test running in `.running.json`.
2. The test is made LINES lines long, as a test of LINES/30 s at 30 sets/s would be: every time
   in its state, its lines and its UTM samples is moved back by that span, and LINES lines (the
   last real line as their pattern: the rig's 9 tags, 3 cameras; a beam loaded to its peak and
   softening to 3.2 mm) and the UTM samples of that span (--utm-hz, 50 by default: the demo's
   UTM is polled at 50 Hz) are appended, ending before now.
3. A new daemon is started inside a memory cgroup of its own (cgroup v1,
   /sys/fs/cgroup/memory/<name>: memory.limit_in_bytes and memory.memsw.limit_in_bytes =
   LIMIT); it resumes the test (the measurement runs beside it), and after a few seconds the
   test is stopped: the daemon makes the report, its plots and (Chromium, a child, in the same
   cgroup) the PDF, and writes `test.json`.
4. Printed: the cgroup's peak memory (memory.max_usage_in_bytes: it counts the page cache, which
   the kernel reclaims at the limit), the peak of its processes' own memory (rss + shmem, read
   from memory.stat every 50 ms: what cannot be reclaimed, what an OOM is about), the daemon's
   own peak RSS (VmHWM), whether the limit was reached or an OOM happened, the time from the
   stop to `test.json`, the load (`uptime`) before and after.

Root is needed (the cgroup). Disk: ~2.4 kB a line (2.4 GB for 1 000 000 lines), deleted at the
end unless --keep.

usage: stop_memory.py [--lines N] [--utm-hz HZ] [--limit-gb G] [--keep] [--dir D | --reuse D] BINARY
"""
import argparse
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time

CGROUP_ROOT = "/sys/fs/cgroup/memory"
PERIOD_NS = 33_333_333  # 30 sets/s


def uptime():
    return open("/proc/loadavg").read().split()[:3]


def wait_for(what, check, timeout_s):
    end = time.time() + timeout_s
    while time.time() < end:
        v = check()
        if v:
            return v
        time.sleep(0.2)
    sys.exit(f"stop_memory: timed out waiting for {what}")


def whole_lines(path):
    try:
        text = open(path).read()
    except FileNotFoundError:
        return []
    return text[: text.rfind("\n") + 1].splitlines()


class Daemon:
    """A `tagdeflect demo --tests` daemon, its stderr in a file; optionally in a cgroup."""

    def __init__(self, binary, work, tests, tag, started, cgroup=None):
        self.log_path = os.path.join(work, f"daemon-{tag}.log")
        self.log = open(self.log_path, "w")

        def into_cgroup():
            if cgroup:
                with open(os.path.join(cgroup, "cgroup.procs"), "w") as f:
                    f.write(str(os.getpid()))

        self.p = subprocess.Popen(
            [binary, "demo", "--tests", tests, "--http", "127.0.0.1:0"],
            stdout=subprocess.DEVNULL, stderr=self.log, preexec_fn=into_cgroup)
        started.append(self)
        text = wait_for("the daemon's address and token", self.ready, 120)
        self.url = re.search(r"live page: (http://[0-9.:]+)/", text).group(1)

    def text(self):
        return open(self.log_path, errors="replace").read()

    def ready(self):
        if self.p.poll() is not None:
            sys.exit(f"stop_memory: the daemon ended ({self.p.returncode}):\n{self.text()[-3000:]}")
        t = self.text()
        return t if "live page: " in t and "control token: " in t else None

    def hwm_kb(self):
        for line in open(f"/proc/{self.p.pid}/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
        return None


def test_cli(binary, url, tests, *args):
    o = subprocess.run([binary, "test", "--url", url, "--token-file", os.path.join(tests, ".token"), *args],
                       capture_output=True, text=True, timeout=3600)
    if o.returncode != 0:
        sys.exit(f"stop_memory: tagdeflect test {' '.join(args)}: {o.stderr}")
    return json.loads(o.stdout)


def shift_times(v, by_ns):
    """Every `t_ns` / `*_t_ns` integer in a JSON value moved back by `by_ns`."""
    if isinstance(v, dict):
        return {k: (x - by_ns if (k == "t_ns" or k.endswith("_t_ns")) and isinstance(x, int) and x > 10**18
                    else shift_times(x, by_ns)) for k, x in v.items()}
    if isinstance(v, list):
        return [shift_times(x, by_ns) for x in v]
    return v


def shift_file(path, by_ns):
    lines = whole_lines(path)
    with open(path, "w") as f:
        for l in lines:
            f.write(json.dumps(shift_times(json.loads(l), by_ns), separators=(",", ":")) + "\n")
    return lines


def curve(k, n):
    """Net deflection (mm) and load (kN) of line k of n: up to the peak, then softening."""
    d = 3.2 * k / max(n - 1, 1)
    p = 45.0 * d / 0.06 if d < 0.06 else 15.0 + 30.0 * math.exp(-(d - 0.06) / 0.4)
    return d, p


def extend(folder, n, utm_hz):
    """Appends n lines and the UTM samples of their span at utm_hz to the test's files (see the
    module doc); the lines are written from a template of the last real line."""
    feed, utm = os.path.join(folder, "feed.jsonl"), os.path.join(folder, "utm.jsonl")
    last = json.loads(whole_lines(feed)[-1])
    for k in ("events", "partial_set"):
        last.pop(k, None)
    if "test" in last:
        last["test"].pop("zeroing", None)
    for c in last.get("cameras", []):
        c["frame"] = True
    mid = {t["id"] for t in last["tags"] if abs(t["pos_mm"][0]) < 50.0}
    # Each changing value a marker in the template's text, replaced line by line.
    last.update(seq="@SEQ", t_ns="@T", load_kN="@P", stroke_mm="@S", net_deflection_mm="@D",
                net_deflection_rate_mm_per_min=round(3.2 / (n / 1800.0), 6))
    for tag in last["tags"]:
        tag["disp_mm"] = [0.0, 0.0, "@Z" if tag["id"] in mid else 0.0]
    parts = re.split(r'"@(SEQ|T|P|S|D|Z)"', json.dumps(last, separators=(",", ":")))
    last_utm = max((json.loads(l)["t_ns"] for l in whole_lines(utm)), default=0)
    seq0 = json.loads(whole_lines(feed)[-1])["seq"] + 1
    t0 = max(json.loads(whole_lines(feed)[-1])["t_ns"], last_utm) + PERIOD_NS
    utm_period_ns = int(1e9 / utm_hz)
    t_utm = t0 - utm_period_ns // 2
    with open(feed, "a") as f, open(utm, "a") as u:
        for k in range(n):
            d, p = curve(k, n)
            t = t0 + k * PERIOD_NS
            v = {"SEQ": str(seq0 + k), "T": str(t), "P": f"{p:.4f}", "S": f"{1.3 * d:.5f}", "D": f"{d:.5f}", "Z": f"{-d:.5f}"}
            f.write("".join(v[x] if i % 2 else x for i, x in enumerate(parts)) + "\n")
            while t_utm < t + PERIOD_NS - utm_period_ns // 2:
                du, pu = curve((t_utm - t0) / PERIOD_NS, n)
                u.write(f'{{"t_ns":{t_utm},"load_kN":{pu:.6f},"stroke_mm":{1.3 * du:.6f}}}\n')
                t_utm += utm_period_ns
    return os.path.getsize(feed), os.path.getsize(utm)


class Sampler(threading.Thread):
    """The cgroup's processes' own memory (rss + shmem from memory.stat), every 50 ms."""

    def __init__(self, cgroup, csv):
        super().__init__(daemon=True)
        self.cgroup, self.csv, self.stop, self.peak, self.peak_at = cgroup, csv, False, 0, None
        self.peak_rss = self.peak_shmem = 0

    def run(self):
        t0, written = time.time(), -1
        with open(self.csv, "w") as out:
            out.write("t_s,rss_mib,shmem_mib,cache_mib\n")
            while not self.stop:
                stat = dict(l.split() for l in open(os.path.join(self.cgroup, "memory.stat")))
                rss, shmem = int(stat["total_rss"]), int(stat.get("total_shmem", 0))
                if rss + shmem > self.peak:
                    self.peak, self.peak_at, self.peak_rss, self.peak_shmem = rss + shmem, time.time(), rss, shmem
                if int(time.time() - t0) > written:
                    written = int(time.time() - t0)
                    out.write(f"{written},{rss / 2**20:.0f},{shmem / 2**20:.0f},{int(stat['total_cache']) / 2**20:.0f}\n")
                    out.flush()
                time.sleep(0.05)


def read_int(cgroup, name):
    return int(open(os.path.join(cgroup, name)).read().split()[0])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("binary")
    ap.add_argument("--lines", type=int, default=1_000_000)
    ap.add_argument("--limit-gb", type=float, default=2.0)
    ap.add_argument("--utm-hz", type=float, default=50.0, help="UTM samples a second (the demo's UTM is polled at 50 Hz)")
    ap.add_argument("--keep", action="store_true", help="keep the work folder")
    ap.add_argument("--dir", default=None, help="make the work folder here")
    ap.add_argument("--reuse", default=None, help="a work folder kept (--keep) by an earlier run whose test was left "
                    "running: resumed and stopped again, without making the test anew")
    a = ap.parse_args()
    binary = os.path.abspath(a.binary)
    work = os.path.abspath(a.reuse) if a.reuse else tempfile.mkdtemp(prefix="stop-memory-", dir=a.dir)
    tests = os.path.join(work, "tests")
    cgroup = os.path.join(CGROUP_ROOT, f"tagdeflect-stop-memory-{os.getpid()}")
    print(f"work folder {work}; load {uptime()}", flush=True)
    daemons = []
    try:
        run(a, binary, work, tests, cgroup, daemons)
    finally:
        for d in daemons:
            if d.p.poll() is None:
                d.p.kill()
                d.p.wait()
        if os.path.isdir(cgroup):
            try:
                os.rmdir(cgroup)
            except OSError as e:
                print(f"cgroup {cgroup} not removed: {e}")
        if not a.keep:
            shutil.rmtree(work, ignore_errors=True)


def run(a, binary, work, tests, cgroup, daemons):
    if a.reuse:
        folder = json.load(open(os.path.join(tests, ".running.json")))["folder"]
        return measure(a, binary, work, tests, cgroup, daemons, folder)
    # 1. A test, killed mid-way.
    d = Daemon(binary, work, tests, "first", daemons)
    st = test_cli(binary, d.url, tests, "start", "--specimen", "LONG1", "--standard", "astm-c1609")
    folder = st["folder"] if os.path.isabs(st["folder"]) else os.path.join(os.getcwd(), st["folder"])
    wait_for("20 lines of the test", lambda: len(whole_lines(os.path.join(folder, "feed.jsonl"))) >= 20, 300)
    d.p.send_signal(signal.SIGKILL)
    d.p.wait()

    # 2. Made LINES lines long.
    span_ns = a.lines * PERIOD_NS + 60 * 10**9
    t = time.time()
    state_path = os.path.join(tests, ".running.json")
    state = shift_times(json.load(open(state_path)), span_ns)
    json.dump(state, open(state_path, "w"))
    shift_file(os.path.join(folder, "feed.jsonl"), span_ns)
    shift_file(os.path.join(folder, "utm.jsonl"), span_ns)
    feed_b, utm_b = extend(folder, a.lines, a.utm_hz)
    print(f"test {st['id']}: {a.lines} lines and their UTM samples at {a.utm_hz:g} Hz appended in {time.time() - t:.0f} s; feed.jsonl {feed_b / 1e9:.2f} GB, "
          f"utm.jsonl {utm_b / 1e6:.0f} MB", flush=True)

    measure(a, binary, work, tests, cgroup, daemons, folder)


def measure(a, binary, work, tests, cgroup, daemons, folder):
    """3. The test resumed inside the cgroup and stopped (or, left while being stopped, completed
    by the new daemon at its start); the figures printed."""
    stopping = json.load(open(os.path.join(tests, ".running.json")))["state"] == "stopping"
    os.mkdir(cgroup)
    limit = int(a.limit_gb * 2**30)
    for name in ("memory.limit_in_bytes", "memory.memsw.limit_in_bytes"):
        with open(os.path.join(cgroup, name), "w") as f:
            f.write(str(limit))
    load_before = uptime()
    t_start = time.time()
    sampler = Sampler(cgroup, os.path.join(work, "memory.csv"))
    sampler.start()
    d = Daemon(binary, work, tests, "resumed", daemons, cgroup)
    if stopping:
        # The daemon was killed during the stop: the new one completes the folder at its start.
        t_resumed = t_stop = time.time()
        before_stop = 0
    else:
        wait_for("the resumed test's lines", lambda: "resumed from its zero" in d.text(), 600)
        t_resumed = time.time()
        time.sleep(10)
        before_stop = sampler.peak
        t_stop = time.time()
        stop = subprocess.run([binary, "test", "--url", d.url, "--token-file", os.path.join(tests, ".token"), "stop"],
                              capture_output=True, text=True, timeout=3600)
        print(f"stop answered {stop.returncode} after {time.time() - t_stop:.1f} s: {stop.stdout.strip()[:300]} "
              f"{stop.stderr.strip()[:300]}", flush=True)
    done = lambda: os.path.exists(os.path.join(folder, "test.json")) or d.p.poll() is not None
    # A long test's report takes longer than the client waits for the stop's answer: the
    # folder's test.json (or the daemon's end) tells when the stop is through.
    wait_for("test.json", done, 3600)
    t_done = time.time()
    time.sleep(2)
    hwm_kb = d.hwm_kb() if d.p.poll() is None else None
    if d.p.poll() is None:
        d.p.send_signal(signal.SIGTERM)
    code = d.p.wait(timeout=1200)
    sampler.stop = True
    sampler.join()
    load_after = uptime()

    oom = open(os.path.join(cgroup, "memory.oom_control")).read().split()
    mb = lambda b: f"{b / 2**20:.0f} MiB"
    print(f"lines in the feed {sum(1 for _ in open(os.path.join(folder, 'feed.jsonl')))}; limit {mb(limit)}; daemon exit {code}")
    print(f"resumed in {t_resumed - t_start:.1f} s; stop to test.json {t_done - t_stop:.1f} s; "
          f"load (uptime) {' '.join(load_before)} -> {' '.join(load_after)}")
    print(f"peak of the processes' own memory (rss + shmem): {mb(sampler.peak)} "
          f"(rss {mb(sampler.peak_rss)}, shmem {mb(sampler.peak_shmem)}) at {sampler.peak_at - t_stop:+.1f} s from the stop; "
          f"before the stop {mb(before_stop)}; the timeline: {sampler.csv}")
    print(f"daemon's own peak RSS (VmHWM): {mb(hwm_kb * 1024) if hwm_kb else 'not read (the daemon ended)'}")
    print(f"cgroup memory.max_usage_in_bytes (page cache included): {mb(read_int(cgroup, 'memory.max_usage_in_bytes'))}; "
          f"failcnt {read_int(cgroup, 'memory.failcnt')}; oom_control {' '.join(oom)}")
    if not os.path.exists(os.path.join(folder, "test.json")):
        sys.exit(f"stop_memory: no test.json; the daemon's log: {d.log_path}\n{d.text()[-2000:]}")
    report = json.load(open(os.path.join(folder, "report", "report.json")))
    pdf = [f for f in os.listdir(os.path.join(folder, "report")) if f.endswith(".pdf")]
    print(f"report: valid {report.get('valid')}, P1 {report.get('P1')}, f150 {report.get('f150')}; PDF {pdf or 'none'}; "
          f"lines in test.json {json.load(open(os.path.join(folder, 'test.json'))).get('lines')}")


if __name__ == "__main__":
    main()
