"""Turntable driver: a Dynamixel servo turns the plate to commanded angles (dynamixel_sdk, no ROS).

`Turntable(TurntableConfig(...))` opens the serial port, finds the servo, puts an X-series servo
(Protocol 2.0) in extended-position (multi-turn) mode with a trapezoidal velocity profile, and
turns the plate with `rotate_to` / `rotate_by`, waiting until it has settled. `open(torque=False)`
and `set_torque(False)` leave the plate free (torque off) until `set_torque(True)`, as a lifecycle
node does. Angles are plate angles in radians, after the gear ratio and the zero offset. Failures
raise typed `DeviceError`s with a hint. Timeouts and CRC errors are retried, and a dropped serial
port is reopened.
All port access holds one lock, so a ROS timer may call `angle()` while `rotate_to` runs in
another thread.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import termios
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from dynamixel_sdk import COMM_RX_TIMEOUT, COMM_SUCCESS, PacketHandler, PortHandler

from n2d_common.errors import Cancelled, ConfigError, DeviceError

log = logging.getLogger(__name__)

SUPPORTED_BAUDS = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600,
                   1000000, 1152000, 2000000, 2500000, 3000000, 3500000, 4000000)

# X-series control table (Protocol 2.0).
ADDR_MODEL_NUMBER = 0
ADDR_DRIVE_MODE = 10
ADDR_OPERATING_MODE = 11
ADDR_VELOCITY_LIMIT = 44
ADDR_TORQUE_ENABLE = 64
ADDR_HARDWARE_ERROR_STATUS = 70
ADDR_PROFILE_ACCELERATION = 108
ADDR_PROFILE_VELOCITY = 112
ADDR_GOAL_POSITION = 116
ADDR_MOVING = 122
ADDR_PRESENT_VELOCITY = 128
ADDR_PRESENT_POSITION = 132
EXTENDED_POSITION_MODE = 4
DRIVE_MODE_TIME_BASED = 0x04
EXTENDED_POSITION_RANGE = 1_048_575

# AX / MX control table (Protocol 1.0).
P1_ADDR_TORQUE_ENABLE = 24
P1_ADDR_GOAL_POSITION = 30
P1_ADDR_MOVING_SPEED = 32
P1_ADDR_PRESENT_POSITION = 36
P1_ADDR_MOVING = 46

MODEL_NAMES = {1020: "XM430-W350", 1030: "XM430-W210", 1060: "XL430-W250", 1000: "XH430-W350",
               1010: "XH430-W210", 1120: "XM540-W270", 1100: "XM540-W150",
               12: "AX-12A", 18: "AX-18A", 300: "AX-12W", 29: "MX-28", 310: "MX-64", 320: "MX-106"}
AX_MODELS = (12, 18, 300)

# Hardware error status bits -> (what happened, what to do). Protocol 1.0 error-byte bits are mapped onto these.
HARDWARE_ERRORS = {
    0x01: ("input voltage out of range",
           "check the servo supply (XM430: 10-14.8 V, 12 V recommended), then reboot the servo"),
    0x04: ("overheating",
           "let the servo cool down and lighten the load, then reboot the servo"),
    0x08: ("motor encoder malfunction",
           "power-cycle the servo; if it persists the servo needs service"),
    0x10: ("electrical shock or insufficient power",
           "check that the power supply can deliver the servo's current, then reboot the servo"),
    0x20: ("overload",
           "remove what blocks the plate, then reboot the servo (power-cycle or Turntable.reboot())"),
}
_P1_HARDWARE_BITS = {0x01: 0x01, 0x04: 0x04, 0x20: 0x20}
_RESULT_ERRORS = {1: "failed to process the instruction", 2: "undefined or wrong instruction",
                  3: "CRC mismatch", 4: "value out of range", 5: "wrong data length",
                  6: "value above its limit", 7: "address not writable/readable now (EEPROM while torque on?)"}
_P1_RESULT_ERRORS = {0x02: "angle limit", 0x08: "value out of range", 0x10: "checksum", 0x40: "instruction"}


class ServoCommError(DeviceError):
    """Communication with the servo failed after all retries (corrupt or missing replies)."""


class ServoNotResponding(ServoCommError):
    """The servo does not answer at all (power, cable, id, baud rate or protocol)."""


class ServoDisconnected(DeviceError):
    """The serial port went away and could not be reopened."""


class ServoRejected(DeviceError):
    """The servo answered but refused the instruction (range, access, ...)."""


class ServoHardwareError(DeviceError):
    """The servo flagged a hardware error and, per its Shutdown setting, turned its torque off."""

    def __init__(self, servo_id: int, bits: int | None):
        self.bits = bits
        if bits is None:
            message, hint = "a hardware error (its status could not be read)", "reboot or power-cycle the servo"
        else:
            found = [HARDWARE_ERRORS[b] for b in sorted(HARDWARE_ERRORS) if bits & b]
            message = ", ".join(what for what, _ in found) or f"hardware error status 0x{bits:02x}"
            hint = "; ".join(fix for _, fix in found) or "reboot or power-cycle the servo"
        super().__init__(f"servo {servo_id} reports {message}; its torque is off", hint)


class MoveTimeout(DeviceError):
    """The plate did not settle at its goal in time."""


class _PortLost(Exception):
    """Internal: the serial port failed with an I/O error or disappeared."""


@dataclass
class TurntableConfig:
    port: str = "/dev/ttyUSB0"
    """Serial port of the U2D2 / USB adapter (a stable /dev/serial/by-id/... path is best)."""
    baud: int = 57600
    """Baud rate the servo is set to (X-series factory default: 57600)."""
    servo_id: int = 1
    """Dynamixel ID of the turntable servo (0..252; factory default 1)."""
    protocol: float = 2.0
    """Dynamixel protocol: 2.0 for X-series (multi-turn, velocity profile), or 1.0 for older
    AX/MX servos (single-turn position control only: the plate range is the servo's range
    divided by gear_ratio, no acceleration profile, no hardware-error register or reboot)."""
    gear_ratio: float = 1.0
    """Servo turns per plate turn (1.0 for a plate mounted on the servo horn)."""
    velocity_limit_rad_s: float = 0.8
    """Plate cruise speed [rad/s] (profile velocity); clamped to the servo's velocity limit."""
    acceleration_rad_s2: float = 2.0
    """Plate acceleration [rad/s^2] (profile acceleration); 0 means as fast as the servo can."""
    zero_offset_rad: float = 0.0
    """Raw plate angle [rad] that is reported as 0 (homing)."""
    settle_tolerance_rad: float = 0.002
    """A move is done when the plate stays this close to its goal [rad] ..."""
    settle_time_s: float = 0.3
    """... for this long [s] with the servo's moving flag off."""
    move_timeout_s: float = 10.0
    """Give up on a move this long [s] after its velocity profile should have ended."""
    poll_period_s: float = 0.02
    """Period [s] of position polling while a move runs."""
    retries: int = 3
    """Extra tries of one transaction after a timeout or CRC error."""
    reconnect_attempts: int = 5
    """Tries to reopen the port after it dropped (USB unplugged); 0 disables reconnection."""
    reconnect_backoff_s: float = 0.2
    """Wait before the first reconnect try [s]; doubles each try, up to 2 s."""

    def __post_init__(self):
        if not self.port:
            raise ValueError("port must not be empty")
        if self.baud not in SUPPORTED_BAUDS:
            raise ValueError(f"baud {self.baud} is not supported; use one of {', '.join(map(str, SUPPORTED_BAUDS))}")
        if not 0 <= self.servo_id <= 252:
            raise ValueError(f"servo_id must be in 0..252, got {self.servo_id}")
        if self.protocol not in (1.0, 2.0):
            raise ValueError(f"protocol must be 1.0 or 2.0, got {self.protocol}")
        for name in ("gear_ratio", "velocity_limit_rad_s", "settle_tolerance_rad", "move_timeout_s",
                     "poll_period_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("acceleration_rad_s2", "settle_time_s", "retries", "reconnect_attempts",
                     "reconnect_backoff_s"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not math.isfinite(self.zero_offset_rad):
            raise ValueError(f"zero_offset_rad must be finite, got {self.zero_offset_rad}")


@dataclass(frozen=True)
class _Family:
    """Units of one servo family."""

    ticks_per_rev: float
    velocity_unit_rpm: float
    max_velocity_units: int
    position_range: tuple[int, int] | None
    """Goal position range in ticks for single-turn servos; None for multi-turn."""


X_SERIES = _Family(4096, 0.229, 32767, None)
AX_SERIES = _Family(1024 * 360 / 300, 0.111, 1023, (0, 1023))
MX_SERIES_P1 = _Family(4096, 0.114, 1023, (0, 4095))
ACCELERATION_UNIT_RPM2 = 214.577

ProgressCallback = Callable[[float, float, str, float], None]
"""on_progress(angle_rad, fraction 0..1, stage "moving"/"settling", eta_s)."""


class Turntable:
    """A servo-driven turntable; use as a context manager or call `open()` / `close()`.

    Args:
        cfg: port, servo and motion settings.
    """

    def __init__(self, cfg: TurntableConfig | None = None):
        self.cfg = cfg or TurntableConfig()
        self.model_number: int | None = None
        self._family = X_SERIES if self.cfg.protocol == 2.0 else MX_SERIES_P1
        self._packet = PacketHandler(self.cfg.protocol)
        self._port: PortHandler | None = None
        self._lock = threading.RLock()
        self._opened = False
        self._reconnecting = False
        self._generation = 0
        self._turn_offset_ticks = 0
        self._velocity_units: int | None = None
        self._velocity_limit_units = 32767
        self._goal_ticks: int | None = None
        self._target_rad: float | None = None
        self._torque_wanted = True

    # ---------------------------------------------------------------- lifecycle
    def open(self, torque: bool = True) -> Turntable:
        """Open the port, find the servo, configure it and, with `torque`, turn its torque on; returns self.

        With `torque` false the torque is turned off (the plate turns freely) until `set_torque(True)`.
        """
        if self._opened:
            return self
        self._torque_wanted = torque
        self._connect_first()
        try:
            self._configure()
        except BaseException:
            self.close()
            raise
        log.info("turntable: servo %d on %s is a %s", self.cfg.servo_id, self.cfg.port,
                 MODEL_NAMES.get(self.model_number, f"model {self.model_number}"))
        return self

    def close(self) -> None:
        """Turn the torque off and close the port (safe to call twice)."""
        with self._lock:
            self._opened = False
            if self._port is None:
                return
            try:
                self._packet.write1ByteTxRx(self._port, self.cfg.servo_id, self._addr_torque(), 0)
            except (OSError, termios.error):
                pass
            self._close_port()

    def __enter__(self) -> Turntable:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def is_open(self) -> bool:
        return self._opened

    def set_torque(self, on: bool) -> None:
        """Turn the servo's torque on (holding the plate where it is) or off (the plate turns freely).

        The choice survives a reconnect and a reboot. Turning it on raises ServoHardwareError while the
        servo reports a hardware error (only a reboot clears it).
        """
        with self._lock:
            self._target_rad = None
            if on:
                self._write_goal(self._present_ticks())
                self._write(self._addr_torque(), 1, 1, "torque on")
                self._torque_wanted = True
            else:
                self._torque_wanted = False
                self._write(self._addr_torque(), 1, 0, "torque off", check_alert=False)

    def torque(self) -> bool:
        """Whether the servo's torque is on now (read from the servo)."""
        return bool(self._read(self._addr_torque(), 1, "read torque", check_alert=False))

    # ---------------------------------------------------------------- motion
    def angle(self, check_alert: bool = False) -> float:
        """Plate angle now [rad], multi-turn, after gear ratio and zero offset.

        With `check_alert`, a hardware error the servo flags in its reply raises ServoHardwareError.
        """
        return self._ticks_to_angle(self._present_ticks(check_alert=check_alert))

    def rotate_to(self, angle_rad: float, velocity_rad_s: float | None = None,
                  on_progress: ProgressCallback | None = None,
                  cancel: threading.Event | None = None) -> float:
        """Turn the plate to `angle_rad` and wait until it settles; returns the reached angle [rad].

        Args:
            angle_rad: goal plate angle [rad] (multi-turn: 4*pi is two turns).
            velocity_rad_s: plate cruise speed for this move [rad/s] (default: the config's).
            on_progress: called each poll with (angle_rad, fraction, stage, eta_s).
            cancel: when set, the plate is braked to a stop and `Cancelled` is raised.

        Raises:
            Cancelled, MoveTimeout, ServoHardwareError, ServoCommError, ServoDisconnected.
        """
        if not math.isfinite(angle_rad):
            raise ConfigError(f"rotate_to: angle must be finite, got {angle_rad}")
        if not self._torque_wanted:
            raise DeviceError("rotate_to: the servo's torque is off", "call set_torque(True) first")
        goal = self._angle_to_ticks(angle_rad)
        self._set_velocity(velocity_rad_s or self.cfg.velocity_limit_rad_s)
        start = self._present_ticks()
        self._target_rad = None
        self._write_goal(goal)
        generation = self._generation
        ticks_per_rad = self._ticks_per_plate_rad()
        tolerance = self.cfg.settle_tolerance_rad * ticks_per_rad
        profile_s = self._profile_time(abs(goal - start))
        t0 = time.monotonic()
        deadline = t0 + profile_s + self.cfg.settle_time_s + self.cfg.move_timeout_s
        settled_since = None
        while True:
            if cancel is not None and cancel.is_set():
                self.stop()
                raise Cancelled(f"rotation to {math.degrees(angle_rad):.1f} deg cancelled at "
                                f"{math.degrees(self.angle()):.1f} deg", "rotate again to continue")
            if self._generation != generation:  # reconnected: make sure the servo still has our goal
                self._write_goal(goal)
                generation = self._generation
            ticks = self._present_ticks()
            moving = self._read(self._addr_moving(), 1, "read moving")
            now = time.monotonic()
            error = abs(goal - ticks)
            if not moving and error <= tolerance:
                settled_since = now if settled_since is None else settled_since
                if now - settled_since >= self.cfg.settle_time_s:
                    reached = self._ticks_to_angle(ticks)
                    self._target_rad = angle_rad
                    if on_progress is not None:
                        on_progress(reached, 1.0, "settling", 0.0)
                    return reached
            else:
                settled_since = None
            if on_progress is not None:
                fraction = 1.0 - error / abs(goal - start) if goal != start else 1.0
                settle_left = self.cfg.settle_time_s - (now - settled_since if settled_since else 0.0)
                eta = max(0.0, t0 + profile_s - now) + settle_left
                stage = "settling" if not moving and error <= tolerance else "moving"
                on_progress(self._ticks_to_angle(ticks), min(max(fraction, 0.0), 1.0), stage, eta)
            if now > deadline:
                raise MoveTimeout(
                    f"plate did not settle at {math.degrees(angle_rad):.1f} deg within {deadline - t0:.1f} s "
                    f"(it is at {math.degrees(self._ticks_to_angle(ticks)):.1f} deg, moving={bool(moving)})",
                    "check that nothing blocks the plate and that the servo has power; "
                    "raise move_timeout_s or settle_tolerance_rad if it is just slow")
            time.sleep(self.cfg.poll_period_s)

    def rotate_by(self, delta_rad: float, **kwargs) -> float:
        """Turn the plate by `delta_rad` from the last reached goal (so steps do not drift) or from here."""
        base = self._target_rad if self._target_rad is not None else self.angle()
        return self.rotate_to(base + delta_rad, **kwargs)

    def stop(self) -> None:
        """Brake the plate to a stop with the profile deceleration (goal = where it can stop)."""
        ticks = self._present_ticks(check_alert=False)
        if self.cfg.protocol == 2.0:
            velocity = _signed(self._read(ADDR_PRESENT_VELOCITY, 4, "read velocity", check_alert=False))
            v = velocity * X_SERIES.velocity_unit_rpm / 60 * X_SERIES.ticks_per_rev  # ticks/s
            a = self._acceleration_units() * ACCELERATION_UNIT_RPM2 / 3600 * X_SERIES.ticks_per_rev
            ticks += int(round(math.copysign(v * v / (2 * a), v))) if a > 0 and v else 0
        self._target_rad = None
        self._write_goal(ticks)

    def reboot(self) -> None:
        """Reboot the servo (clears a hardware error such as overload) and restore its settings.

        The X-series forgets its multi-turn count on reboot; the driver keeps the plate angle
        continuous assuming the shaft moved less than half a turn while it was off. Works on a
        turntable whose `open()` failed with a hardware error, and leaves it open.
        """
        if self.cfg.protocol != 2.0:
            raise DeviceError("reboot needs Protocol 2.0", "power-cycle the servo instead")
        with self._lock:
            if not self._opened:
                self._connect_first()
            before = self._present_ticks(check_alert=False)
            self._transact("reboot", lambda ph, port: (None, *ph.reboot(port, self.cfg.servo_id)), check_alert=False)
            deadline = time.monotonic() + 3.0
            while True:
                time.sleep(0.1)
                _, result, _ = self._packet.ping(self._port, self.cfg.servo_id)
                if result == COMM_SUCCESS:
                    break
                if time.monotonic() > deadline:
                    raise ServoNotResponding(f"servo {self.cfg.servo_id} did not come back after a reboot",
                                             "check its power and cable")
            after = _signed(self._read(ADDR_PRESENT_POSITION, 4, "read position", check_alert=False))
            turns = round((before - after) / self._family.ticks_per_rev)
            self._turn_offset_ticks += int(turns * self._family.ticks_per_rev)
            self._velocity_units = None
            self._configure()

    def hardware_error(self) -> int:
        """The servo's hardware error status bits (0: none; Protocol 2.0 only)."""
        if self.cfg.protocol != 2.0:
            return 0
        return self._read(ADDR_HARDWARE_ERROR_STATUS, 1, "read hardware error", check_alert=False)

    # ---------------------------------------------------------------- units
    def _ticks_per_plate_rad(self) -> float:
        return self._family.ticks_per_rev * self.cfg.gear_ratio / (2 * math.pi)

    def _ticks_to_angle(self, ticks: int) -> float:
        return (ticks + self._turn_offset_ticks) / self._ticks_per_plate_rad() - self.cfg.zero_offset_rad

    def _angle_to_ticks(self, angle_rad: float) -> int:
        raw = (angle_rad + self.cfg.zero_offset_rad) * self._ticks_per_plate_rad()
        ticks = int(round(raw)) - self._turn_offset_ticks
        lo, hi = self._family.position_range or (-EXTENDED_POSITION_RANGE, EXTENDED_POSITION_RANGE)
        if not lo <= ticks <= hi:
            span = (hi - lo) / self._ticks_per_plate_rad()
            raise ConfigError(f"plate angle {math.degrees(angle_rad):.1f} deg is outside the servo's range "
                              f"({math.degrees(span):.0f} deg of plate travel)",
                              "use an X-series servo (Protocol 2.0, multi-turn) or change zero_offset_rad")
        return ticks

    def _velocity_to_units(self, velocity_rad_s: float) -> int:
        rpm = velocity_rad_s * self.cfg.gear_ratio * 60 / (2 * math.pi)
        return max(1, min(self._family.max_velocity_units, int(round(rpm / self._family.velocity_unit_rpm))))

    def _acceleration_units(self) -> int:
        if self.cfg.protocol != 2.0 or self.cfg.acceleration_rad_s2 == 0:
            return 0
        rpm2 = self.cfg.acceleration_rad_s2 * self.cfg.gear_ratio * 3600 / (2 * math.pi)
        return max(1, min(32767, int(round(rpm2 / ACCELERATION_UNIT_RPM2))))

    def _profile_time(self, distance_ticks: float) -> float:
        """Duration [s] of the velocity profile over `distance_ticks`, with the servo's quantised units."""
        v = (self._velocity_units or 1) * self._family.velocity_unit_rpm / 60 * self._family.ticks_per_rev
        a = self._acceleration_units() * ACCELERATION_UNIT_RPM2 / 3600 * self._family.ticks_per_rev
        if a <= 0:
            return distance_ticks / v
        if distance_ticks >= v * v / a:
            return distance_ticks / v + v / a
        return 2 * math.sqrt(distance_ticks / a)

    # ---------------------------------------------------------------- servo registers
    def _addr_torque(self) -> int:
        return ADDR_TORQUE_ENABLE if self.cfg.protocol == 2.0 else P1_ADDR_TORQUE_ENABLE

    def _addr_moving(self) -> int:
        return ADDR_MOVING if self.cfg.protocol == 2.0 else P1_ADDR_MOVING

    def _present_ticks(self, check_alert: bool = True) -> int:
        if self.cfg.protocol == 2.0:
            return _signed(self._read(ADDR_PRESENT_POSITION, 4, "read position", check_alert))
        return self._read(P1_ADDR_PRESENT_POSITION, 2, "read position", check_alert)

    def _write_goal(self, ticks: int) -> None:
        if self.cfg.protocol == 2.0:
            self._write(ADDR_GOAL_POSITION, 4, ticks, "write goal position")
        else:
            self._write(P1_ADDR_GOAL_POSITION, 2, ticks, "write goal position")
        self._goal_ticks = ticks

    def _set_velocity(self, velocity_rad_s: float) -> None:
        if velocity_rad_s <= 0:
            raise ConfigError(f"velocity must be > 0 rad/s, got {velocity_rad_s}")
        self._write_velocity_units(self._velocity_to_units(velocity_rad_s))

    def _write_velocity_units(self, units: int, force: bool = False) -> None:
        if self.cfg.protocol == 2.0 and units > self._velocity_limit_units:
            log.warning("turntable: speed clamped to the servo's velocity limit (%d x 0.229 rpm)",
                        self._velocity_limit_units)
            units = self._velocity_limit_units
        if force or units != self._velocity_units:
            addr = ADDR_PROFILE_VELOCITY if self.cfg.protocol == 2.0 else P1_ADDR_MOVING_SPEED
            self._write(addr, 4 if self.cfg.protocol == 2.0 else 2, units, "write profile velocity")
            self._velocity_units = units

    def _configure(self) -> None:
        """Mode, profile and torque from the config (after open, reconnect and reboot)."""
        if self.cfg.protocol == 2.0:
            hw = self._read(ADDR_HARDWARE_ERROR_STATUS, 1, "read hardware error", check_alert=False)
            if hw:
                raise ServoHardwareError(self.cfg.servo_id, hw)
            torque = self._read(ADDR_TORQUE_ENABLE, 1, "read torque")
            mode = self._read(ADDR_OPERATING_MODE, 1, "read operating mode")
            drive = self._read(ADDR_DRIVE_MODE, 1, "read drive mode")
            if mode != EXTENDED_POSITION_MODE or drive & DRIVE_MODE_TIME_BASED:
                if torque:  # the EEPROM area is locked while torque is on
                    self._write(ADDR_TORQUE_ENABLE, 1, 0, "torque off")
                    torque = 0
                self._write(ADDR_OPERATING_MODE, 1, EXTENDED_POSITION_MODE, "write operating mode")
                self._write(ADDR_DRIVE_MODE, 1, drive & ~DRIVE_MODE_TIME_BASED, "write drive mode")
            self._velocity_limit_units = self._read(ADDR_VELOCITY_LIMIT, 4, "read velocity limit") or 32767
            self._write(ADDR_PROFILE_ACCELERATION, 4, self._acceleration_units(), "write profile acceleration")
        else:
            torque = self._read(P1_ADDR_TORQUE_ENABLE, 1, "read torque")
        self._write_velocity_units(self._velocity_units or self._velocity_to_units(self.cfg.velocity_limit_rad_s),
                                   force=True)
        if self._torque_wanted and not torque:  # hold where it is: goal = present before the torque comes on
            self._write_goal(self._present_ticks())
            self._write(self._addr_torque(), 1, 1, "torque on")
        elif torque and not self._torque_wanted:
            self._write(self._addr_torque(), 1, 0, "torque off")

    # ---------------------------------------------------------------- transactions
    def _read(self, addr: int, size: int, what: str, check_alert: bool = True) -> int:
        sid = self.cfg.servo_id
        fn = {1: "read1ByteTxRx", 2: "read2ByteTxRx", 4: "read4ByteTxRx"}[size]
        return self._transact(what, lambda ph, port: getattr(ph, fn)(port, sid, addr), check_alert)

    def _write(self, addr: int, size: int, value: int, what: str, check_alert: bool = True) -> None:
        sid = self.cfg.servo_id
        fn = {1: "write1ByteTxRx", 2: "write2ByteTxRx", 4: "write4ByteTxRx"}[size]
        value &= (1 << (8 * size)) - 1
        self._transact(what, lambda ph, port: (None, *getattr(ph, fn)(port, sid, addr, value)), check_alert)

    def _transact(self, what: str, fn, check_alert: bool = True):
        """Run `fn(packet_handler, port) -> (value, comm_result, error)` with retries and reconnection."""
        while True:
            generation = self._generation
            try:
                return self._transact_once(what, fn, check_alert)
            except _PortLost as lost:
                if self._reconnecting:
                    raise
                self._reconnect(lost, generation)

    def _transact_once(self, what: str, fn, check_alert: bool):
        with self._lock:
            if self._port is None:
                if not self._opened and not self._reconnecting:
                    raise DeviceError("the turntable is not open", "call Turntable.open() first")
                raise _PortLost("port is closed")
            result, corrupt = COMM_SUCCESS, False
            for _ in range(self.cfg.retries + 1):
                try:
                    value, result, error = fn(self._packet, self._port)
                except (OSError, termios.error) as exc:  # serial.SerialException is an OSError
                    self._port.is_using = False
                    raise _PortLost(f"{type(exc).__name__}: {exc}") from exc
                except (IndexError, ValueError):
                    # The SDK indexes into a reply it could not fully read (a late, partial or garbled
                    # packet, seen on loaded machines): drop the rest and retry like a CRC error.
                    self._port.is_using = False
                    self._port.clearPort()
                    corrupt = True
                    continue
                if result == COMM_SUCCESS:
                    self._check_status(error, what, check_alert)
                    return value
                corrupt |= result != COMM_RX_TIMEOUT
            if not os.path.exists(self.cfg.port):
                raise _PortLost(f"{self.cfg.port} disappeared")
            where = f"servo {self.cfg.servo_id} on {self.cfg.port}"
            tries = self.cfg.retries + 1
            if not corrupt:
                raise ServoNotResponding(f"{where} did not answer ({what}, {tries} tries)",
                                         "check the servo's power and cable")
            raise ServoCommError(f"{where}: {what} failed {tries} times: corrupt replies (CRC error or garbled packet)",
                                 "check the cable and connectors; lower the baud rate on long cables")

    def _check_status(self, error: int, what: str, check_alert: bool) -> None:
        sid = self.cfg.servo_id
        if self.cfg.protocol == 2.0:
            if error & 0x80 and check_alert:
                try:
                    hw, result, _ = self._packet.read1ByteTxRx(self._port, sid, ADDR_HARDWARE_ERROR_STATUS)
                except (OSError, termios.error):
                    hw, result = 0, None
                raise ServoHardwareError(sid, hw if result == COMM_SUCCESS else None)
            code = error & 0x7F
            if code:
                raise ServoRejected(f"servo {sid} refused to {what}: {_RESULT_ERRORS.get(code, f'error {code}')}",
                                    "this is a driver bug or a servo setting out of range; check with Dynamixel Wizard")
            return
        hw = sum(bit for p1, bit in _P1_HARDWARE_BITS.items() if error & p1)
        if hw and check_alert:
            raise ServoHardwareError(sid, hw)
        other = [name for bit, name in _P1_RESULT_ERRORS.items() if error & bit]
        if other:
            raise ServoRejected(f"servo {sid} refused to {what}: {', '.join(other)} error",
                                "check the angle limits and values with Dynamixel Wizard")

    # ---------------------------------------------------------------- connection
    def _connect_first(self) -> None:
        """Connect for `open()` / `reboot()`: errors name the port, id, baud and protocol."""
        try:
            self._connect(scan=True)
        except _PortLost as exc:
            raise DeviceError(f"serial port {self.cfg.port} failed while talking to the servo: {exc}",
                              "check the USB cable and `ls /dev/ttyUSB*`") from None
        self._opened = True

    def _connect(self, scan: bool = False) -> None:
        """Open the port and ping the servo; `scan` adds a broadcast ping to the error message."""
        port = PortHandler(self.cfg.port)
        try:
            ok = port.setBaudRate(self.cfg.baud)
        except (OSError, termios.error) as exc:
            raise _port_error(self.cfg.port, exc) from None
        if not ok:
            raise ConfigError(f"baud rate {self.cfg.baud} is not supported by the serial port {self.cfg.port}")
        with self._lock:
            self._port = port
        model, result, error = None, COMM_SUCCESS, 0
        try:
            for _ in range(self.cfg.retries + 1):
                model, result, error = self._packet.ping(port, self.cfg.servo_id)
                if result == COMM_SUCCESS:
                    break
        except (OSError, termios.error) as exc:
            self._close_port()
            raise _PortLost(f"{type(exc).__name__}: {exc}") from exc
        if result != COMM_SUCCESS:
            found = self._scan() if scan else ""
            self._close_port()
            raise ServoNotResponding(
                f"servo id {self.cfg.servo_id} does not answer on {self.cfg.port} "
                f"(tried {self.cfg.baud} baud, protocol {self.cfg.protocol}){found}",
                "check the servo's power (12 V) and cable, and set servo_id/baud/protocol to the servo's "
                "(scan with DYNAMIXEL Wizard 2.0; X-series factory default: id 1, 57600 baud, protocol 2.0)")
        self.model_number = model
        if self.cfg.protocol == 1.0:
            self._family = AX_SERIES if model in AX_MODELS else MX_SERIES_P1

    def _scan(self) -> str:
        """'; ids answering: [..]' from a broadcast ping (Protocol 2.0), for error messages."""
        if self.cfg.protocol != 2.0:
            return ""
        try:
            found, result = self._packet.broadcastPing(self._port)
        except (OSError, termios.error):
            return ""
        if result != COMM_SUCCESS or not found:
            return "; no servo answers a broadcast ping at this baud rate"
        return f"; ids answering at this baud rate: {sorted(found)}"

    def _close_port(self) -> None:
        with self._lock:
            port, self._port = self._port, None
        if port is not None:
            try:
                port.closePort()
            except (OSError, termios.error):
                pass

    def _reconnect(self, lost: _PortLost, generation: int) -> None:
        """Reopen the port after it dropped, restore the servo settings; raise when it stays gone."""
        with self._lock:
            if generation != self._generation:
                return  # another thread reconnected meanwhile
            if not self._opened:
                raise DeviceError("the turntable is not open", "call Turntable.open() first")
            log.warning("turntable: lost %s (%s); reconnecting", self.cfg.port, lost)
            self._close_port()
            delay, last = self.cfg.reconnect_backoff_s, str(lost)
            self._reconnecting = True
            try:
                for attempt in range(1, self.cfg.reconnect_attempts + 1):
                    time.sleep(delay)
                    delay = min(2 * delay, 2.0) or 0.05
                    try:
                        self._connect()
                        self._configure()
                    except ServoHardwareError:
                        raise
                    except (DeviceError, _PortLost) as exc:
                        last = str(exc)
                        self._close_port()
                        continue
                    self._generation += 1
                    log.info("turntable: reconnected to %s (attempt %d)", self.cfg.port, attempt)
                    return
            finally:
                self._reconnecting = False
            raise ServoDisconnected(
                f"lost the servo on {self.cfg.port} and could not reconnect in "
                f"{self.cfg.reconnect_attempts} attempts (last error: {last})",
                "check the USB cable and the servo's power (ls /dev/ttyUSB*), then open the turntable again")


def _signed(value: int) -> int:
    return value - (1 << 32) if value & (1 << 31) else value


def _port_error(port: str, exc: BaseException) -> DeviceError:
    """One clear line for a port that cannot be opened."""
    code = getattr(exc, "errno", None)
    reason = os.strerror(code) if code else str(exc).splitlines()[0]
    hints = {
        errno.ENOENT: "no such device: is the adapter plugged in? list ports with `ls /dev/ttyUSB* /dev/ttyACM*`",
        errno.EACCES: "permission denied: add yourself to the dialout group "
                      "(sudo usermod -aG dialout $USER, then log out and in)",
        errno.EBUSY: "another program holds the port (Dynamixel Wizard?); close it",
    }
    hint = hints.get(code, "check the port name (ls /dev/ttyUSB* /dev/ttyACM*) and that you are in the dialout group")
    return DeviceError(f"cannot open serial port {port}: {reason}", hint)
