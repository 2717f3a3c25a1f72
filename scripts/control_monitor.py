#!/usr/bin/env python3
"""Reads tagdeflect's control output (SPEC "Control output") over Modbus TCP, as a
testing machine's controller would, and prints one JSON line per read.

Usage: control_monitor.py HOST PORT [--interval S] [--reads N] [--try-write]

Connects (retrying for up to 60 s while the daemon starts), then reads input registers
0-11 every S seconds (default 0.05) until N reads (default: until the server goes away) and
prints {"t": wall-clock s, "value": mm, "um": µm, "sigma": mm, "valid": 0|1, "seq": ..,
"age_ms": .., "heartbeat": .., "rate_mm_per_min": ..}. With --try-write it first tries to
write a holding register and prints {"write_refused": true|false}: the control output must
refuse every write. Needs pymodbus (scripts/setup.sh puts it in target/test-venv).
"""

import argparse
import json
import struct
import sys
import time

from pymodbus.client import ModbusTcpClient


def decode(regs):
    def f32(i):
        return struct.unpack(">f", struct.pack(">HH", regs[i], regs[i + 1]))[0]

    def i32(i):
        return struct.unpack(">i", struct.pack(">HH", regs[i], regs[i + 1]))[0]

    return {
        "value": f32(0),
        "um": i32(2),
        "sigma": f32(4),
        "valid": regs[6],
        "seq": regs[7],
        "age_ms": regs[8],
        "heartbeat": regs[9],
        "rate_mm_per_min": f32(10),
    }


def read_input(client, address, count):
    return client.read_input_registers(address, count=count)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("host")
    ap.add_argument("port", type=int)
    ap.add_argument("--interval", type=float, default=0.05)
    ap.add_argument("--reads", type=int, default=0)
    ap.add_argument("--try-write", action="store_true")
    a = ap.parse_args()
    client = ModbusTcpClient(a.host, port=a.port, timeout=2, retries=0)
    deadline = time.time() + 60
    while not client.connect():
        if time.time() > deadline:
            print(f"control_monitor: cannot connect to {a.host}:{a.port}", file=sys.stderr)
            return 1
        time.sleep(0.1)
    if a.try_write:
        try:
            r = client.write_register(0, 1)
            refused = r.isError()
        except Exception:  # an exception reply raised by some versions
            refused = True
        print(json.dumps({"write_refused": bool(refused)}), flush=True)
    n = 0
    while a.reads == 0 or n < a.reads:
        try:
            r = read_input(client, 0, 12)
        except Exception as e:  # the server went away: the daemon stopped
            print(f"control_monitor: read failed ({e}); stopping", file=sys.stderr)
            break
        if r.isError():
            print(f"control_monitor: read refused: {r}", file=sys.stderr)
            break
        out = decode(r.registers)
        out["t"] = time.time()
        print(json.dumps(out), flush=True)
        n += 1
        time.sleep(a.interval)
    client.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
