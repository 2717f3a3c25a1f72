#!/usr/bin/env python3
"""A PI controller closing the loop on tagdeflect's control output, as a testing machine's
controller would: it reads the net deflection over Modbus TCP (tagdeflect's read-only input
registers, SPEC "Control output") and commands the actuator's stroke rate of a (simulated)
testing machine so that the net deflection rises at a constant rate (ASTM C1609 style).

Usage: pi_controller.py (--control HOST:PORT | --analog HOST:PORT [--volts-per-mm V]
                        [--offset-v V]) --machine HOST:PORT --rate MM_PER_MIN
                        --duration S [--hz 50] [--kp 300] [--ki 300] [--log FILE]

The value comes from one of two sources:
  --control  tagdeflect's control output (input registers 0-1 value, 6 valid, 9 heartbeat);
  --analog   the analog output's DAQ, read as a controller reads its analog input: the DAC's
             volts (LabJack T-series DAC0, holding registers 1000-1001, FLOAT32 high word
             first) converted back with --volts-per-mm and --offset-v, and the valid line
             (FIO0, holding register 2000). tagdeflect writes these registers
             (`[output.analog]`); nothing of tagdeflect's own registers is read.

Safety behaviour (docs/control.md): while valid = 0, or (control output) the heartbeat has
not moved for 200 ms, or a read fails, the actuator is *held* (rate 0) and the setpoint's
clock stops; at the end the actuator is held. The machine's actuator rate is holding registers 0-1 (f32,
mm/min, high word first) of the simulated machine (crates/sim/src/machine.rs).
Logs one JSON line per cycle: t, valid, value, setpoint, command.
"""

import argparse
import json
import struct
import sys
import time

from pymodbus.client import ModbusTcpClient


def f32_words(v):
    return list(struct.unpack(">HH", struct.pack(">f", v)))


def f32(regs, i):
    return struct.unpack(">f", struct.pack(">HH", regs[i], regs[i + 1]))[0]


def connect(addr, deadline):
    host, port = addr.rsplit(":", 1)
    c = ModbusTcpClient(host, port=int(port), timeout=1, retries=0)
    while not c.connect():
        if time.time() > deadline:
            raise SystemExit(f"pi_controller: cannot connect to {addr}")
        time.sleep(0.1)
    return c


def control_reader(client):
    """The control output's value, valid flag and heartbeat (None when the read failed)."""

    def read():
        r = client.read_input_registers(0, count=12)
        if r.isError():
            return None
        regs = r.registers
        return f32(regs, 0), regs[6] == 1, regs[9]

    return read


def analog_reader(client, volts_per_mm, offset_v):
    """The DAQ's DAC0 volts back in mm and its valid line (no heartbeat: the line is it)."""

    def read():
        dac = client.read_holding_registers(1000, count=2)
        line = client.read_holding_registers(2000, count=1)
        if dac.isError() or line.isError():
            return None
        volts = f32(dac.registers, 0)
        return (volts - offset_v) / volts_per_mm, line.registers[0] == 1, None

    return read


def main():
    ap = argparse.ArgumentParser()
    source = ap.add_mutually_exclusive_group(required=True)
    source.add_argument("--control")
    source.add_argument("--analog")
    ap.add_argument("--volts-per-mm", type=float, default=1.0)
    ap.add_argument("--offset-v", type=float, default=0.0)
    ap.add_argument("--machine", required=True)
    ap.add_argument("--rate", type=float, required=True, help="target net-deflection rate, mm/min")
    ap.add_argument("--duration", type=float, required=True)
    ap.add_argument("--hz", type=float, default=50.0)
    ap.add_argument("--kp", type=float, default=300.0, help="mm/min of stroke rate per mm of error")
    ap.add_argument("--ki", type=float, default=300.0, help="mm/min per mm·s")
    ap.add_argument("--log")
    a = ap.parse_args()
    log = open(a.log, "w") if a.log else None
    deadline = time.time() + 60
    ctl = connect(a.control or a.analog, deadline)
    read = control_reader(ctl) if a.control else analog_reader(ctl, a.volts_per_mm, a.offset_v)
    mach = connect(a.machine, deadline)
    period = 1.0 / a.hz
    t0 = time.time()
    last_beat, beat_at = None, t0
    start, sp_clock, integ = None, 0.0, 0.0
    last = time.time()
    while time.time() - t0 < a.duration:
        now = time.time()
        dt = now - last
        last = now
        value, valid = float("nan"), False
        try:
            got = read()
            if got is not None:
                value, valid, beat = got
                if beat is None or beat != last_beat:
                    last_beat, beat_at = beat, now
        except Exception:
            pass
        ok = valid and now - beat_at < 0.2
        setpoint = None
        if ok:
            if start is None:
                start = value
            sp_clock += dt
            setpoint = start + a.rate / 60.0 * sp_clock
            e = setpoint - value
            integ += e * dt
            command = a.rate + a.kp * e + a.ki * integ
        else:
            command = 0.0  # hold the stroke
        mach.write_registers(0, f32_words(command))
        if log:
            log.write(json.dumps({"t": now, "valid": ok, "value": value, "setpoint": setpoint, "command": command}) + "\n")
        time.sleep(max(0.0, period - (time.time() - now)))
    mach.write_registers(0, f32_words(0.0))
    ctl.close()
    mach.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
