"""Emulated Dynamixel XM430-W350 servo speaking Protocol 2.0 on a pseudo-terminal, for the real dynamixel_sdk.

Three layers, each usable on its own:

* `ServoEmulator`: the servo itself, with no I/O. It holds the X-series control table, answers
  instruction packets (`handle_bytes`) and moves the shaft along the X-series trapezoidal
  velocity profile in wall-clock time. `shaft_angle_rad()` and `plate_angle_rad()` give the
  true angle (the simulator's ground truth), and `inject()` adds faults.
* `PtyServo`: runs an emulator on `pty.openpty()` in a daemon thread, with a stable symlink
  (`link`) to the slave tty. A driver opens `servo.port` exactly as it would open
  `/dev/ttyUSB0`. `disconnect()` / `reconnect()` pull and replug the "USB cable".
* `python -m n2d_sim.servo --link PATH [--id 1] [--control SOCKET]`: a standalone process that
  serves until SIGTERM or SIGINT. `ServoControl(SOCKET)` is its client (faults, state).

In-process use (the ROS sim node)::

    servo = PtyServo(ServoEmulator(servo_id=1, gear_ratio=1.0), link="/tmp/n2d/ttyDXL").start()
    # configure the driver with port="/tmp/n2d/ttyDXL"
    servo.emulator.plate_angle_rad()   # true multi-turn plate angle [rad], thread-safe
    servo.stop()

Not emulated: current/PWM operating modes, indirect addresses, the reverse-direction drive mode
bit, fast sync/bulk read, factory reset, baud-rate mismatch (a pty has no baud rate), and
Protocol 1.0 (its packets are ignored, like noise on the bus).
"""

from __future__ import annotations

import argparse
import enum
import math
import os
import pty
import queue
import select
import signal
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Client, Listener
from pathlib import Path

from n2d_common.errors import DeviceError

MODEL_XM430_W350 = 1020
FIRMWARE_VERSION = 48
BROADCAST_ID = 0xFE
TICKS_PER_REV = 4096
VELOCITY_UNIT_RPM = 0.229
"""Velocity unit of the X-series [rev/min]."""
ACCELERATION_UNIT_RPM2 = 214.577
"""Profile acceleration unit of the X-series [rev/min^2]."""
CURRENT_UNIT_MA = 2.69
EXTENDED_POSITION_RANGE = 1_048_575
MAX_PACKET_LENGTH = 1024
BOOT_TIME_S = 0.05
"""After a REBOOT the servo ignores the bus this long."""
STALE_PACKET_S = 0.1
"""A partial packet older than this is dropped when new bytes arrive (resync)."""

HEADER = b"\xff\xff\xfd\x00"

# Instructions.
INST_PING = 0x01
INST_READ = 0x02
INST_WRITE = 0x03
INST_REG_WRITE = 0x04
INST_ACTION = 0x05
INST_REBOOT = 0x08
INST_CLEAR = 0x10
INST_STATUS = 0x55
INST_SYNC_READ = 0x82
INST_SYNC_WRITE = 0x83
INST_BULK_READ = 0x92
INST_BULK_WRITE = 0x93

# Result codes of the status packet's error byte (bit 7 is the hardware alert).
ERR_RESULT_FAIL = 1
ERR_INSTRUCTION = 2
ERR_CRC = 3
ERR_DATA_RANGE = 4
ERR_DATA_LENGTH = 5
ERR_DATA_LIMIT = 6
ERR_ACCESS = 7
ERR_ALERT = 0x80

# Hardware error status bits (address 70).
HW_INPUT_VOLTAGE = 0x01
HW_OVERHEATING = 0x04
HW_MOTOR_ENCODER = 0x08
HW_ELECTRICAL_SHOCK = 0x10
HW_OVERLOAD = 0x20

# Operating modes.
MODE_VELOCITY = 1
MODE_POSITION = 3
MODE_EXTENDED_POSITION = 4


@dataclass(frozen=True)
class Field:
    """One entry of the control table."""

    name: str
    addr: int
    size: int
    default: int = 0
    lo: int | None = None
    """Smallest writable value; None for a read-only field."""
    hi: int | None = None
    signed: bool = False

    @property
    def writable(self) -> bool:
        return self.lo is not None

    @property
    def eeprom(self) -> bool:
        return self.addr < 64


def _rw(name: str, addr: int, size: int, default: int, lo: int, hi: int, signed: bool = False) -> Field:
    return Field(name, addr, size, default, lo, hi, signed)


def _ro(name: str, addr: int, size: int, default: int = 0, signed: bool = False) -> Field:
    return Field(name, addr, size, default, None, None, signed)


FIELDS: tuple[Field, ...] = (
    # EEPROM area: writable only while torque is off.
    _ro("model_number", 0, 2, MODEL_XM430_W350),
    _ro("model_information", 2, 4),
    _ro("firmware_version", 6, 1, FIRMWARE_VERSION),
    _rw("id", 7, 1, 1, 0, 252),
    _rw("baud_rate", 8, 1, 1, 0, 7),
    _rw("return_delay_time", 9, 1, 250, 0, 254),
    _rw("drive_mode", 10, 1, 0, 0, 13),
    _rw("operating_mode", 11, 1, MODE_POSITION, 0, 16),
    _rw("secondary_id", 12, 1, 255, 0, 255),
    _rw("protocol_type", 13, 1, 2, 2, 2),
    _rw("homing_offset", 20, 4, 0, -1_044_479, 1_044_479, signed=True),
    _rw("moving_threshold", 24, 4, 10, 0, 1023),
    _rw("temperature_limit", 31, 1, 80, 0, 100),
    _rw("max_voltage_limit", 32, 2, 160, 60, 160),
    _rw("min_voltage_limit", 34, 2, 95, 60, 160),
    _rw("pwm_limit", 36, 2, 885, 0, 885),
    _rw("current_limit", 38, 2, 1193, 0, 1193),
    _rw("velocity_limit", 44, 4, 200, 0, 1023),
    _rw("max_position_limit", 48, 4, 4095, 0, 4095),
    _rw("min_position_limit", 52, 4, 0, 0, 4095),
    _rw("shutdown", 63, 1, HW_OVERLOAD | HW_ELECTRICAL_SHOCK | HW_OVERHEATING, 0, 255),
    # RAM area.
    _rw("torque_enable", 64, 1, 0, 0, 1),
    _rw("led", 65, 1, 0, 0, 1),
    _rw("status_return_level", 68, 1, 2, 0, 2),
    _ro("registered_instruction", 69, 1),
    _ro("hardware_error_status", 70, 1),
    _rw("velocity_i_gain", 76, 2, 1920, 0, 16383),
    _rw("velocity_p_gain", 78, 2, 100, 0, 16383),
    _rw("position_d_gain", 80, 2, 0, 0, 16383),
    _rw("position_i_gain", 82, 2, 0, 0, 16383),
    _rw("position_p_gain", 84, 2, 800, 0, 16383),
    _rw("feedforward_2nd_gain", 88, 2, 0, 0, 16383),
    _rw("feedforward_1st_gain", 90, 2, 0, 0, 16383),
    _rw("bus_watchdog", 98, 1, 0, 0, 127),
    _rw("goal_pwm", 100, 2, 885, -885, 885, signed=True),
    _rw("goal_current", 102, 2, 1193, -1193, 1193, signed=True),
    _rw("goal_velocity", 104, 4, 0, -1023, 1023, signed=True),
    _rw("profile_acceleration", 108, 4, 0, 0, 32767),
    _rw("profile_velocity", 112, 4, 0, 0, 32767),
    _rw("goal_position", 116, 4, 0, -EXTENDED_POSITION_RANGE, EXTENDED_POSITION_RANGE, signed=True),
    _ro("realtime_tick", 120, 2),
    _ro("moving", 122, 1),
    _ro("moving_status", 123, 1),
    _ro("present_pwm", 124, 2, signed=True),
    _ro("present_current", 126, 2, signed=True),
    _ro("present_velocity", 128, 4, signed=True),
    _ro("present_position", 132, 4, signed=True),
    _ro("velocity_trajectory", 136, 4, signed=True),
    _ro("position_trajectory", 140, 4, signed=True),
    _ro("present_input_voltage", 144, 2, 120),
    _ro("present_temperature", 146, 1, 32),
)
BY_NAME = {f.name: f for f in FIELDS}
BY_ADDR = {f.addr: f for f in FIELDS}
TABLE_SIZE = max(f.addr + f.size for f in FIELDS)


class ServoFault(enum.StrEnum):
    """Faults that can be injected; `OVERLOAD` latches until REBOOT, the others until `NONE`."""

    NONE = "none"
    NO_REPLY = "no_reply"
    """Keep listening but never answer (a dead servo, wrong baud, broken data line)."""
    BAD_CRC = "bad_crc"
    """Answer with a corrupted CRC (electrical noise)."""
    OVERLOAD = "overload"
    """Hardware error bit 5: torque off, alert bit in every status packet; cleared only by REBOOT."""
    DISCONNECT = "disconnect"
    """The USB cable is pulled: the pty hangs up and the symlink goes (PtyServo only)."""


# ---------------------------------------------------------------- packet helpers

def _crc_table() -> list[int]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes) -> int:
    """The Dynamixel Protocol 2.0 CRC-16 (polynomial 0x8005, initial value 0, not reflected)."""
    crc = 0
    for byte in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ byte) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Byte stuffing: every FF FF FD in instruction+parameters gets an extra FD."""
    out = bytearray()
    for byte in body:
        out.append(byte)
        if byte == 0xFD and out[-3:-1] == b"\xff\xff":
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    """Undo `stuff`: FF FF FD FD becomes FF FF FD."""
    out = bytearray()
    i = 0
    while i < len(body):
        out.append(body[i])
        if body[i] == 0xFD and out[-3:-1] == b"\xff\xff" and i + 1 < len(body) and body[i + 1] == 0xFD:
            i += 1
        i += 1
    return bytes(out)


def make_packet(servo_id: int, body: bytes) -> bytes:
    """A complete Protocol 2.0 packet (header, id, length, stuffed body, CRC) around `body`."""
    stuffed = stuff(body)
    length = len(stuffed) + 2
    packet = HEADER + bytes([servo_id, length & 0xFF, length >> 8]) + stuffed
    crc = crc16(packet)
    return packet + bytes([crc & 0xFF, crc >> 8])


def _to_bytes(value: int, size: int) -> bytes:
    return (value & ((1 << (8 * size)) - 1)).to_bytes(size, "little")


def _from_bytes(data: bytes, signed: bool) -> int:
    return int.from_bytes(data, "little", signed=signed)


# ---------------------------------------------------------------- motion profile

Segment = tuple[float, float, float]
"""(duration_s, start velocity, acceleration); velocity may jump between segments."""


def plan_move(p0: float, v0: float, p1: float, v_max: float, a_max: float) -> list[Segment]:
    """Time-optimal segments from (p0, v0) to rest at p1 with |v| <= v_max and |a| <= a_max (inf allowed).

    This is the X-series trapezoidal profile: accelerate, cruise at v_max, decelerate; a triangle
    when the distance is too short to reach v_max. A start velocity pointing away from the target
    (or too fast to stop in time) is braked to zero first, so position stays continuous.
    """
    segs: list[Segment] = []
    if math.isinf(a_max):
        d = p1 - p0
        return [(abs(d) / v_max, math.copysign(v_max, d), 0.0)] if d and v_max > 0 else []
    d = p1 - p0
    if v0 * d < 0 or v0 * v0 / (2 * a_max) > abs(d) + 1e-9:
        t = abs(v0) / a_max
        segs.append((t, v0, -math.copysign(a_max, v0)))
        p0 += v0 * t / 2
        v0 = 0.0
        d = p1 - p0
    if abs(d) < 1e-9:
        return segs
    s = math.copysign(1.0, d)
    dist, u = abs(d), abs(v0)
    if u > v_max:
        t = (u - v_max) / a_max
        segs.append((t, s * u, -s * a_max))
        dist -= (u + v_max) / 2 * t
        u = v_max
    d_acc = (v_max * v_max - u * u) / (2 * a_max)
    d_dec = v_max * v_max / (2 * a_max)
    if d_acc + d_dec <= dist:
        segs += [((v_max - u) / a_max, s * u, s * a_max),
                 ((dist - d_acc - d_dec) / v_max, s * v_max, 0.0),
                 (v_max / a_max, s * v_max, -s * a_max)]
    else:
        peak = math.sqrt(a_max * dist + u * u / 2)
        segs += [((peak - u) / a_max, s * u, s * a_max), (peak / a_max, s * peak, -s * a_max)]
    return [seg for seg in segs if seg[0] > 0]


def plan_velocity(v0: float, v1: float, a_max: float) -> list[Segment]:
    """Segments ramping the velocity from v0 to v1 and holding it forever (velocity mode)."""
    if math.isinf(a_max) or v0 == v1:
        return [(math.inf, v1, 0.0)]
    return [(abs(v1 - v0) / a_max, v0, math.copysign(a_max, v1 - v0)), (math.inf, v1, 0.0)]


def velocity_units_to_ticks_s(units: float) -> float:
    """X-series velocity units (0.229 rpm) to encoder ticks per second."""
    return units * VELOCITY_UNIT_RPM / 60.0 * TICKS_PER_REV


def acceleration_units_to_ticks_s2(units: float) -> float:
    """X-series profile acceleration units (214.577 rev/min^2) to ticks/s^2; 0 means infinite."""
    return units * ACCELERATION_UNIT_RPM2 / 3600.0 * TICKS_PER_REV if units else math.inf


# ---------------------------------------------------------------- the servo

class ServoEmulator:
    """An XM430-W350 without I/O: control table, Protocol 2.0 packet handling and motion.

    Thread-safe: `handle_bytes` runs in the pty thread while another thread reads the true angle.

    Args:
        servo_id: Dynamixel ID (0..252).
        gear_ratio: servo turns per turntable-plate turn, for `plate_angle_rad`.
        clock: time source in seconds; motion follows it (default `time.monotonic`).
    """

    def __init__(self, servo_id: int = 1, gear_ratio: float = 1.0, clock: Callable[[], float] = time.monotonic):
        if not 0 <= servo_id <= 252:
            raise ValueError(f"servo_id must be in 0..252, got {servo_id}")
        if gear_ratio <= 0:
            raise ValueError(f"gear_ratio must be > 0, got {gear_ratio}")
        self.gear_ratio = gear_ratio
        self._clock = clock
        self._lock = threading.RLock()
        self._table = bytearray(TABLE_SIZE)
        for f in FIELDS:
            self._table[f.addr:f.addr + f.size] = _to_bytes(f.default, f.size)
        self._set("id", servo_id)
        self._rx = bytearray()
        self._rx_time = 0.0
        self.fault = ServoFault.NONE
        self.rx_packets = 0
        self.crc_errors = 0
        self._pos = 0.0      # ticks, register frame without homing offset
        self._vel = 0.0      # ticks/s
        self._acc = 0.0      # ticks/s^2
        self._turn_base = 0  # shaft ticks = _pos + _turn_base (ground truth survives multi-turn resets)
        self._plan: list[Segment] = []
        self._plan_t0 = self._plan_p0 = 0.0
        self._plan_goal: float | None = None
        self._profile_type = 0
        self._registered: list[tuple[Field, int]] | None = None
        self._boot_t = clock()
        self._booting_until = 0.0

    # ---- public API
    @property
    def servo_id(self) -> int:
        return self._get("id")

    def handle_bytes(self, data: bytes, now: float | None = None) -> bytes:
        """Feed bytes received from the bus; return the bytes the servo answers (maybe empty).

        Packets may be split across calls; garbage is skipped up to the next header.
        """
        with self._lock:
            now = self._clock() if now is None else now
            if self._rx and now - self._rx_time > STALE_PACKET_S:
                self._rx.clear()
            self._rx += data
            self._rx_time = now
            out = bytearray()
            while True:
                start = self._rx.find(HEADER)
                if start < 0:
                    del self._rx[:-3]
                    break
                del self._rx[:start]
                if len(self._rx) < 7:
                    break
                length = self._rx[5] | self._rx[6] << 8
                if not 3 <= length <= MAX_PACKET_LENGTH:
                    del self._rx[0]
                    continue
                if len(self._rx) < 7 + length:
                    break
                packet = bytes(self._rx[:7 + length])
                if crc16(packet[:-2]) != (packet[-2] | packet[-1] << 8):
                    self.crc_errors += 1
                    del self._rx[0]  # resync: a real packet may hide inside the bad one
                    if packet[4] == self.servo_id and now >= self._booting_until:
                        out += self._reply(ERR_CRC)
                    continue
                del self._rx[:7 + length]
                if now >= self._booting_until:
                    out += self._dispatch(packet[4], unstuff(packet[7:-2]), now)
            return bytes(out)

    def inject(self, fault: ServoFault | str) -> None:
        """Inject a fault. `NONE` clears no_reply/bad_crc (an overload stays until REBOOT).

        `DISCONNECT` only makes sense on a `PtyServo`; here it acts as `NO_REPLY`.
        """
        fault = ServoFault(fault)
        with self._lock:
            if fault is ServoFault.OVERLOAD:
                self.raise_hardware_error(HW_OVERLOAD)
            else:
                self.fault = fault

    def raise_hardware_error(self, bits: int) -> None:
        """Set hardware error status bits; torque turns off when they are in the Shutdown mask."""
        with self._lock:
            now = self._clock()
            self._advance(now)
            self._set("hardware_error_status", self._get("hardware_error_status") | bits)
            if bits & self._get("shutdown"):
                self._torque_off()

    def shaft_angle_rad(self) -> float:
        """True multi-turn shaft angle now [rad], unaffected by homing offset or reboots."""
        with self._lock:
            self._advance(self._clock())
            return (self._pos + self._turn_base) / TICKS_PER_REV * 2 * math.pi

    def plate_angle_rad(self) -> float:
        """True turntable-plate angle now [rad]: shaft angle / gear_ratio."""
        return self.shaft_angle_rad() / self.gear_ratio

    def state(self) -> dict:
        """A snapshot for the simulator and tests (plain types only)."""
        with self._lock:
            now = self._clock()
            self._refresh(now)
            return {
                "position_rad": (self._pos + self._turn_base) / TICKS_PER_REV * 2 * math.pi,
                "plate_rad": (self._pos + self._turn_base) / TICKS_PER_REV * 2 * math.pi / self.gear_ratio,
                "velocity_rad_s": self._vel / TICKS_PER_REV * 2 * math.pi,
                "moving": bool(self._get("moving")),
                "torque": bool(self._get("torque_enable")),
                "hardware_error": self._get("hardware_error_status"),
                "operating_mode": self._get("operating_mode"),
                "goal_position": self._get("goal_position"),
                "present_position": self._get("present_position"),
                "servo_id": self.servo_id,
                "fault": self.fault.value,
                "rx_packets": self.rx_packets,
                "crc_errors": self.crc_errors,
            }

    def read_field(self, name: str) -> int:
        """Current value of a control-table field (dynamic fields refreshed)."""
        with self._lock:
            self._refresh(self._clock())
            return self._get(name)

    # ---- control table
    def _get(self, name: str) -> int:
        f = BY_NAME[name]
        return _from_bytes(self._table[f.addr:f.addr + f.size], f.signed)

    def _set(self, name: str, value: int) -> None:
        f = BY_NAME[name]
        self._table[f.addr:f.addr + f.size] = _to_bytes(int(value), f.size)

    def _refresh(self, now: float) -> None:
        """Write the dynamic (present_*) fields for time `now`."""
        self._advance(now)
        torque = self._get("torque_enable")
        velocity_units = self._vel * 60.0 / TICKS_PER_REV / VELOCITY_UNIT_RPM
        planned = bool(self._plan) and self._plan_goal is not None
        moving = torque and (planned or abs(velocity_units) > self._get("moving_threshold"))
        goal = self._get("goal_position") - self._get("homing_offset")
        in_position = not planned and abs(goal - self._pos) <= self._get("moving_threshold")
        present = int(round(self._pos)) + self._get("homing_offset")
        current = 0.0
        if torque:
            current = 4 + 0.02 * abs(velocity_units) + 0.004 * abs(self._acc if self._plan else 0.0)
            current = math.copysign(current, self._acc or self._vel or 1.0)
        self._set("realtime_tick", int((now - self._boot_t) * 1000) % 32768)
        self._set("moving", int(bool(moving)))
        self._set("moving_status", (int(in_position and torque) | (2 if planned else 0)
                                    | (self._profile_type << 4 if planned else 0)))
        self._set("present_pwm", int(round(current * 3)) if torque else 0)
        self._set("present_current", int(round(current)))
        self._set("present_velocity", int(round(velocity_units)))
        self._set("present_position", present)
        self._set("velocity_trajectory", int(round(velocity_units)))
        self._set("position_trajectory", present)

    # ---- motion
    def _advance(self, now: float) -> None:
        """Move the shaft along the current plan up to time `now`."""
        if not self._plan:
            return
        t = max(0.0, now - self._plan_t0)
        p = self._plan_p0
        for duration, v0, a in self._plan:
            if t < duration:
                self._pos = p + v0 * t + a * t * t / 2
                self._vel = v0 + a * t
                self._acc = a
                return
            p += v0 * duration + a * duration * duration / 2
            t -= duration
        self._pos = self._plan_goal if self._plan_goal is not None else p
        self._vel = self._acc = 0.0
        self._plan = []

    def _limits(self) -> tuple[float, float]:
        """Profile velocity [ticks/s] and acceleration [ticks/s^2] in force."""
        v_limit = self._get("velocity_limit")
        v_units = self._get("profile_velocity")
        v_units = v_limit if v_units == 0 else min(v_units, v_limit)
        return velocity_units_to_ticks_s(v_units), acceleration_units_to_ticks_s2(self._get("profile_acceleration"))

    def _start_position_move(self, now: float) -> None:
        self._advance(now)
        target = float(self._get("goal_position") - self._get("homing_offset"))
        v_max, a_max = self._limits()
        if v_max <= 0:
            return
        self._plan = plan_move(self._pos, self._vel, target, v_max, a_max)
        self._plan_t0, self._plan_p0, self._plan_goal = now, self._pos, target
        cruise = any(a == 0 for _, _, a in self._plan)
        self._profile_type = 1 if math.isinf(a_max) else (3 if cruise else 2)
        if not self._plan:
            self._pos, self._vel = target, 0.0

    def _start_velocity_move(self, now: float) -> None:
        self._advance(now)
        _, a_max = self._limits()
        target = velocity_units_to_ticks_s(self._get("goal_velocity"))
        self._plan = plan_velocity(self._vel, target, a_max)
        self._plan_t0, self._plan_p0, self._plan_goal = now, self._pos, None
        self._profile_type = 1 if math.isinf(a_max) else 3

    def _torque_off(self) -> None:
        self._set("torque_enable", 0)
        self._plan = []
        self._vel = self._acc = 0.0

    def _wrap_single_turn(self) -> None:
        """Drop the multi-turn count (reboot, position mode): present position back into 0..4095."""
        turns = math.floor(self._pos / TICKS_PER_REV)
        self._pos -= turns * TICKS_PER_REV
        self._turn_base += turns * TICKS_PER_REV

    def _goal_to_present(self) -> None:
        self._set("goal_position", int(round(self._pos)) + self._get("homing_offset"))

    # ---- instructions
    def _reply(self, error: int, params: bytes = b"") -> bytes:
        if self.fault in (ServoFault.NO_REPLY, ServoFault.DISCONNECT):
            return b""
        if self._get("hardware_error_status"):
            error |= ERR_ALERT
        packet = make_packet(self.servo_id, bytes([INST_STATUS, error]) + params)
        if self.fault is ServoFault.BAD_CRC:
            packet = packet[:-2] + bytes([packet[-2] ^ 0xFF, packet[-1] ^ 0x5A])
        return packet

    def _dispatch(self, packet_id: int, body: bytes, now: float) -> bytes:
        me = self.servo_id
        if packet_id not in (me, BROADCAST_ID) or not body:
            return b""
        self.rx_packets += 1
        inst, params = body[0], body[1:]
        broadcast = packet_id == BROADCAST_ID
        level = self._get("status_return_level")
        if inst == INST_PING:
            return self._reply(0, _to_bytes(self._get("model_number"), 2) + bytes([self._get("firmware_version")]))
        if inst == INST_READ:
            if broadcast:
                return b""
            if len(params) != 4:
                return self._reply(ERR_DATA_LENGTH) if level >= 1 else b""
            error, data = self._read(params[0] | params[1] << 8, params[2] | params[3] << 8, now)
            return self._reply(error, data) if level >= 1 else b""
        if inst in (INST_SYNC_READ, INST_BULK_READ):
            return self._group_read(inst, params, now)
        if inst in (INST_SYNC_WRITE, INST_BULK_WRITE):
            self._group_write(inst, params, now)
            return b""
        if inst == INST_WRITE:
            error = ERR_DATA_LENGTH if len(params) < 3 else self._write(params[0] | params[1] << 8, params[2:], now)
        elif inst == INST_REG_WRITE:
            error = ERR_DATA_LENGTH if len(params) < 3 else self._register(params[0] | params[1] << 8, params[2:])
        elif inst == INST_ACTION:
            error = self._action(now)
        elif inst == INST_REBOOT:
            reply = b"" if broadcast or level < 2 else self._reply(0)
            self._reboot(now)
            return reply
        elif inst == INST_CLEAR:
            error = self._clear(params, now)
        else:
            error = ERR_INSTRUCTION
        return b"" if broadcast or level < 2 else self._reply(error)

    def _read(self, addr: int, length: int, now: float) -> tuple[int, bytes]:
        if length == 0 or addr + length > TABLE_SIZE:
            return ERR_ACCESS, b""
        self._refresh(now)
        return 0, bytes(self._table[addr:addr + length])

    def _parse_write(self, addr: int, data: bytes) -> tuple[int, list[tuple[Field, int]]]:
        """Split a write into whole fields and check access and ranges: (error, [(field, value)])."""
        writes = []
        offset = 0
        torque = self._get("torque_enable")
        while offset < len(data):
            f = BY_ADDR.get(addr + offset)
            if f is None or not f.writable:
                return ERR_ACCESS, []
            if offset + f.size > len(data):
                return ERR_DATA_LENGTH, []
            if f.eeprom and torque:
                return ERR_ACCESS, []
            value = _from_bytes(data[offset:offset + f.size], f.signed)
            if not f.lo <= value <= f.hi:
                return ERR_DATA_RANGE, []
            writes.append((f, value))
            offset += f.size
        return 0, writes

    def _write(self, addr: int, data: bytes, now: float) -> int:
        error, writes = self._parse_write(addr, data)
        if not error:
            error = self._apply(writes, now)
        return error

    def _register(self, addr: int, data: bytes) -> int:
        error, writes = self._parse_write(addr, data)
        if not error:
            self._registered = writes
            self._set("registered_instruction", 1)
        return error

    def _action(self, now: float) -> int:
        if self._registered is None:
            return ERR_RESULT_FAIL
        writes, self._registered = self._registered, None
        self._set("registered_instruction", 0)
        return self._apply(writes, now)

    def _apply(self, writes: list[tuple[Field, int]], now: float) -> int:
        """Store checked values and react to them (new goals, torque, mode)."""
        self._advance(now)
        for f, value in writes:
            if f.name == "operating_mode" and value not in (MODE_VELOCITY, MODE_POSITION, MODE_EXTENDED_POSITION):
                return ERR_DATA_RANGE  # current / PWM modes are not emulated
            if f.name == "goal_velocity" and abs(value) > self._get("velocity_limit"):
                return ERR_DATA_LIMIT
        for f, value in writes:
            mode = self._get("operating_mode")
            if f.name == "goal_position" and mode == MODE_POSITION:
                value = min(max(value, self._get("min_position_limit")), self._get("max_position_limit"))
            if f.name == "torque_enable" and value and self._get("hardware_error_status"):
                continue  # after a shutdown only REBOOT brings torque back
            old = self._get(f.name)
            self._set(f.name, value)
            if f.name == "torque_enable":
                if value and not old:
                    self._goal_to_present()
                    if mode == MODE_VELOCITY:
                        self._start_velocity_move(now)
                elif not value:
                    self._torque_off()
            elif f.name == "operating_mode" and value != old:
                self._plan, self._vel = [], 0.0
                if value == MODE_POSITION:
                    self._wrap_single_turn()
                self._goal_to_present()
            elif f.name == "goal_position" and mode in (MODE_POSITION, MODE_EXTENDED_POSITION):
                if self._get("torque_enable"):
                    self._start_position_move(now)
            elif f.name == "goal_velocity" and mode == MODE_VELOCITY and self._get("torque_enable"):
                self._start_velocity_move(now)
        return 0

    def _reboot(self, now: float) -> None:
        self._advance(now)
        self._torque_off()
        for f in FIELDS:
            if not f.eeprom and f.name != "present_input_voltage":
                self._set(f.name, f.default)
        self._registered = None
        self._wrap_single_turn()
        self._goal_to_present()
        self._boot_t = now
        self._booting_until = now + BOOT_TIME_S
        self._rx.clear()

    def _clear(self, params: bytes, now: float) -> int:
        if params != b"\x01\x44\x58\x4c\x22":
            return ERR_DATA_RANGE
        self._refresh(now)
        if self._get("moving"):
            return ERR_RESULT_FAIL
        self._wrap_single_turn()
        return 0

    def _group_read(self, inst: int, params: bytes, now: float) -> bytes:
        me = self.servo_id
        if inst == INST_SYNC_READ:
            if len(params) < 5 or me not in params[4:]:
                return b""
            addr, length = params[0] | params[1] << 8, params[2] | params[3] << 8
        else:
            entries = [params[i:i + 5] for i in range(0, len(params) - 4, 5)]
            mine = [e for e in entries if e[0] == me]
            if not mine:
                return b""
            addr, length = mine[0][1] | mine[0][2] << 8, mine[0][3] | mine[0][4] << 8
        error, data = self._read(addr, length, now)
        return self._reply(error, data)

    def _group_write(self, inst: int, params: bytes, now: float) -> None:
        me = self.servo_id
        if inst == INST_SYNC_WRITE:
            if len(params) < 4:
                return
            addr, length = params[0] | params[1] << 8, params[2] | params[3] << 8
            for i in range(4, len(params) - length, length + 1):
                if params[i] == me:
                    self._write(addr, params[i + 1:i + 1 + length], now)
            return
        i = 0
        while i + 5 <= len(params):
            dxl_id, addr, length = params[i], params[i + 1] | params[i + 2] << 8, params[i + 3] | params[i + 4] << 8
            if dxl_id == me:
                self._write(addr, params[i + 5:i + 5 + length], now)
            i += 5 + length


# ---------------------------------------------------------------- the pseudo-terminal

class PtyServo:
    """Serve a `ServoEmulator` on a pseudo-terminal from a daemon thread.

    `port` is what a driver opens: the symlink `link` when given (stable across `reconnect`),
    else the slave tty name (e.g. /dev/pts/7). The pty is raw, so bytes pass unchanged.

    Args:
        emulator: the servo to serve.
        link: path of a symlink to create to the slave tty (its directory is created).
    """

    def __init__(self, emulator: ServoEmulator, link: str | os.PathLike | None = None):
        self.emulator = emulator
        self.link = Path(link) if link is not None else None
        self._master: int | None = None
        self._slave: int | None = None
        self._slave_name: str | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._wake_r, self._wake_w = -1, -1
        self._requests: queue.Queue = queue.Queue()

    @property
    def port(self) -> str:
        """The serial port a driver should open."""
        if self.link is not None:
            return str(self.link)
        if self._slave_name is None:
            raise DeviceError("PtyServo is not started", "call start() first")
        return self._slave_name

    @property
    def tty(self) -> str | None:
        """The slave tty currently behind `port` (None while disconnected)."""
        return self._slave_name

    @property
    def connected(self) -> bool:
        return self._master is not None

    def start(self) -> PtyServo:
        """Open the pty, create the symlink and start serving; returns self."""
        if self._thread is not None:
            return self
        self._open_pty()
        self._wake_r, self._wake_w = os.pipe()
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name=f"servo-{self.emulator.servo_id}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving, close the pty and remove the symlink (safe to call twice)."""
        if self._thread is not None:
            self._stop.set()
            os.write(self._wake_w, b"x")
            self._thread.join(timeout=5)
            self._thread = None
            os.close(self._wake_r)
            os.close(self._wake_w)
        self._close_pty()

    def disconnect(self) -> None:
        """Pull the cable: the pty hangs up (the driver's reads/writes fail) and the symlink goes."""
        self._in_worker(self._close_pty)

    def reconnect(self) -> None:
        """Plug the cable back: a new pty behind the same symlink; the servo kept its state."""
        self._in_worker(lambda: None if self.connected else self._open_pty())

    def inject(self, fault: ServoFault | str) -> None:
        """Inject a fault; `DISCONNECT` hangs up, `NONE` also reconnects a disconnected port."""
        fault = ServoFault(fault)
        if fault is ServoFault.DISCONNECT:
            self.disconnect()
        else:
            if fault is ServoFault.NONE:
                self.reconnect()
            self.emulator.inject(fault)

    def __enter__(self) -> PtyServo:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ---- internals
    def _open_pty(self) -> None:
        master, slave = pty.openpty()
        tty.setraw(slave)  # no echo, no line editing, no CR/LF mapping: exact bytes both ways
        os.set_blocking(master, False)
        self._master, self._slave, self._slave_name = master, slave, os.ttyname(slave)
        if self.link is not None:
            self.link.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.link.with_name(self.link.name + ".tmp")
            tmp.unlink(missing_ok=True)
            os.symlink(self._slave_name, tmp)
            os.replace(tmp, self.link)

    def _close_pty(self) -> None:
        if self.link is not None and self.link.is_symlink() and os.readlink(self.link) == self._slave_name:
            self.link.unlink()
        for fd in (self._master, self._slave):
            if fd is not None:
                os.close(fd)
        self._master = self._slave = self._slave_name = None

    def _in_worker(self, fn: Callable[[], None]) -> None:
        """Run `fn` in the serving thread (which owns the fds), or here when not serving."""
        if self._thread is None or threading.current_thread() is self._thread:
            fn()
            return
        done = threading.Event()
        box: list[BaseException] = []
        self._requests.put((fn, done, box))
        os.write(self._wake_w, b"x")
        if not done.wait(timeout=5):
            raise DeviceError("servo emulator thread did not answer", "the emulator is stuck; restart it")
        if box:
            raise box[0]

    def _run_requests(self) -> None:
        while not self._requests.empty():
            fn, done, box = self._requests.get()
            try:
                fn()
            except BaseException as exc:  # handed to the caller
                box.append(exc)
            done.set()

    def _serve(self) -> None:
        while not self._stop.is_set():
            master = self._master
            fds = [self._wake_r] + ([master] if master is not None else [])
            ready, _, _ = select.select(fds, [], [], 0.5)
            if self._wake_r in ready:
                os.read(self._wake_r, 512)
                self._run_requests()
                continue  # the fds may have changed
            if master is None or master not in ready:
                continue
            try:
                data = os.read(master, 4096)
            except BlockingIOError:
                continue
            except OSError:
                time.sleep(0.01)
                continue
            reply = self.emulator.handle_bytes(data)
            if reply:
                time.sleep(self.emulator.read_field("return_delay_time") * 2e-6)
                try:
                    os.write(master, reply)
                except OSError:
                    pass  # nobody reads and the buffer is full: the reply is lost, as on a bus


# ---------------------------------------------------------------- control socket

class ControlServer:
    """Answer `ServoControl` requests for a `PtyServo` on an AF_UNIX socket (one thread per client).

    Requests and replies are dicts (see `handle`); the socket file is made owner-only.
    """

    def __init__(self, servo: PtyServo, path: str | os.PathLike, on_shutdown: Callable[[], None] | None = None):
        self.servo = servo
        self.path = Path(path)
        self.on_shutdown = on_shutdown
        self._listener: Listener | None = None
        self._thread: threading.Thread | None = None
        self._closing = False

    def start(self) -> ControlServer:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.unlink(missing_ok=True)
        self._listener = Listener(str(self.path), family="AF_UNIX")
        os.chmod(self.path, 0o600)
        self._thread = threading.Thread(target=self._accept, name="servo-control", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        if self._listener is None:
            return
        self._closing = True
        try:  # wake the blocking accept()
            Client(str(self.path), family="AF_UNIX").close()
        except OSError:
            pass
        self._listener.close()
        self._listener = None
        if self._thread is not None:
            self._thread.join(timeout=2)

    def handle(self, message: dict) -> dict:
        """One request -> one reply; every reply has "ok" and, when not ok, "error".

        {"fault": NAME}          inject a ServoFault ("none", "no_reply", "bad_crc", "overload", "disconnect")
        {"cmd": "disconnect"}    pull the cable;  {"cmd": "reconnect"}: plug it back
        {"cmd": "state"}         state: position_rad (true shaft angle, multi-turn), plate_rad, velocity_rad_s,
                                 moving, torque, hardware_error, operating_mode, goal_position,
                                 present_position, fault, rx_packets, crc_errors, connected, port, tty
        {"cmd": "shutdown"}      stop the standalone process
        """
        if not isinstance(message, dict):
            return {"ok": False, "error": f"expected a dict, got {type(message).__name__}"}
        try:
            if "fault" in message:
                self.servo.inject(message["fault"])
                return {"ok": True, "fault": ServoFault(message["fault"]).value}
            cmd = message.get("cmd")
            if cmd == "disconnect":
                self.servo.disconnect()
            elif cmd == "reconnect":
                self.servo.reconnect()
            elif cmd == "shutdown":
                if self.on_shutdown is not None:
                    self.on_shutdown()
            elif cmd != "state":
                return {"ok": False, "error": f"unknown request {message!r}"}
            return {"ok": True, **self.servo.emulator.state(), "connected": self.servo.connected,
                    "port": self.servo.port, "tty": self.servo.tty}
        except (ValueError, DeviceError, OSError) as exc:
            return {"ok": False, "error": str(exc)}

    def _accept(self) -> None:
        while not self._closing:
            try:
                conn = self._listener.accept()
            except OSError:
                return
            if self._closing:
                conn.close()
                return
            threading.Thread(target=self._talk, args=(conn,), daemon=True).start()

    def _talk(self, conn) -> None:
        with conn:
            while True:
                try:
                    message = conn.recv()
                except (EOFError, OSError):
                    return
                conn.send(self.handle(message))


class ServoControl:
    """Client of a standalone emulator's control socket (`--control PATH`).

    Each call opens a short connection, so one object can be shared by threads.
    """

    def __init__(self, path: str | os.PathLike, timeout_s: float = 5.0):
        self.path = Path(path)
        self.timeout_s = timeout_s

    def request(self, message: dict) -> dict:
        """Send one request dict and return the reply; a refused request raises DeviceError."""
        try:
            with Client(str(self.path), family="AF_UNIX") as conn:
                conn.send(message)
                if not conn.poll(self.timeout_s):
                    raise DeviceError(f"servo emulator at {self.path} did not answer {message!r}",
                                      "is the emulator process still running?")
                reply = conn.recv()
        except (OSError, EOFError) as exc:
            raise DeviceError(f"cannot reach the servo emulator at {self.path}: {exc}",
                              "start it with python -m n2d_sim.servo --link PORT --control PATH") from None
        if not reply.get("ok"):
            raise DeviceError(f"servo emulator refused {message!r}: {reply.get('error')}")
        return reply

    def fault(self, name: ServoFault | str) -> dict:
        """Inject a fault by name: none, no_reply, bad_crc, overload, disconnect."""
        return self.request({"fault": ServoFault(name).value})

    def disconnect(self) -> dict:
        return self.request({"cmd": "disconnect"})

    def reconnect(self) -> dict:
        return self.request({"cmd": "reconnect"})

    def state(self) -> dict:
        """position_rad (true multi-turn shaft angle), moving, torque, hardware_error, ..."""
        return self.request({"cmd": "state"})

    def shutdown(self) -> dict:
        return self.request({"cmd": "shutdown"})

    def wait_ready(self, timeout_s: float = 10.0) -> dict:
        """Wait until the emulator answers and its port exists; returns its state."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                state = self.state()
                if state["connected"] and os.path.exists(state["port"]):
                    return state
            except DeviceError:
                if time.monotonic() > deadline:
                    raise
            if time.monotonic() > deadline:
                raise DeviceError(f"servo emulator at {self.path} did not become ready in {timeout_s} s")
            time.sleep(0.02)


# ---------------------------------------------------------------- standalone process

def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m n2d_sim.servo", description=__doc__.splitlines()[0])
    parser.add_argument("--link", required=True, help="symlink to create to the emulated serial port")
    parser.add_argument("--id", type=int, default=1, help="Dynamixel ID (default 1)")
    parser.add_argument("--gear-ratio", type=float, default=1.0, help="servo turns per plate turn")
    parser.add_argument("--control", help="AF_UNIX socket path for ServoControl (faults, state)")
    args = parser.parse_args(argv)

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    servo = PtyServo(ServoEmulator(servo_id=args.id, gear_ratio=args.gear_ratio), link=args.link).start()
    server = ControlServer(servo, args.control, on_shutdown=stop.set).start() if args.control else None
    print(f"n2d servo emulator: XM430-W350 id {args.id} on {servo.port} -> {servo.tty}", flush=True)
    try:
        while not stop.wait(0.2):
            pass
    finally:
        if server is not None:
            server.close()
        servo.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
