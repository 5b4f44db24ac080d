"""The turntable driver against the emulated XM430-W350 running in another process (real SDK, real pty)."""

from __future__ import annotations

import logging
import math
import threading
import time

import pytest
from dynamixel_sdk import COMM_SUCCESS, PacketHandler, PortHandler

from n2d_capture.turntable import (
    MoveTimeout,
    ServoCommError,
    ServoDisconnected,
    ServoHardwareError,
    ServoNotResponding,
    Turntable,
    TurntableConfig,
)
from n2d_common.config import ConfigError, from_dict
from n2d_common.errors import Cancelled, DeviceError


def fast(sim, **overrides) -> TurntableConfig:
    """A config for quick tests: brisk profile, short settle."""
    values = dict(port=sim.link, velocity_limit_rad_s=3.0, acceleration_rad_s2=20.0, settle_time_s=0.1,
                  reconnect_backoff_s=0.05)
    values.update(overrides)
    return TurntableConfig(**values)


@pytest.mark.timeout(60)
def test_open_configures_extended_position_mode(sim):
    with Turntable(fast(sim)) as table:
        assert table.model_number == 1020
        state = sim.control.state()
        assert state["operating_mode"] == 4 and state["torque"]
        assert table.angle() == pytest.approx(state["plate_rad"], abs=1e-3)
    assert not sim.control.state()["torque"]  # close() releases the plate


@pytest.mark.timeout(60)
def test_torque_off_until_set_torque_and_kept_across_a_reconnect(sim):
    table = Turntable(fast(sim)).open(torque=False)
    try:
        assert not sim.control.state()["torque"] and not table.torque()
        with pytest.raises(DeviceError, match="torque is off"):
            table.rotate_to(1.0)
        table.set_torque(True)
        assert sim.control.state()["torque"] and table.torque()
        assert table.rotate_to(1.0) == pytest.approx(1.0, abs=0.002)
        table.set_torque(False)
        sim.control.disconnect()
        sim.control.reconnect()
        assert table.angle() == pytest.approx(1.0, abs=0.002)  # reconnected, and the torque stays off
        assert not sim.control.state()["torque"]
        sim.control.fault("overload")
        with pytest.raises(ServoHardwareError):
            table.set_torque(True)  # only a reboot clears the error
        table.reboot()
        assert not sim.control.state()["torque"]  # the reboot keeps it off, as asked
    finally:
        table.close()


@pytest.mark.timeout(60)
def test_rotate_90_degrees_takes_the_profile_time_and_settles(sim):
    progress = []
    with Turntable(fast(sim)) as table:
        start = table.angle()
        t0 = time.monotonic()
        reached = table.rotate_to(start + math.pi / 2,
                                  on_progress=lambda *p: progress.append((time.monotonic() - t0, *p)))
    v = 125 * 0.229 * 2 * math.pi / 60  # the servo's quantised profile velocity [rad/s]
    a = 53 * 214.577 * 2 * math.pi / 3600  # and acceleration [rad/s^2]
    expected = (math.pi / 2) / v + v / a  # ~0.68 s
    first_settling = next(t for t, _, _, stage, _ in progress if stage == "settling")
    assert 0.7 * expected < first_settling < 1.3 * expected
    assert reached == pytest.approx(start + math.pi / 2, abs=0.002)
    assert sim.control.state()["plate_rad"] == pytest.approx(start + math.pi / 2, abs=0.002)
    stages = [stage for *_, stage, _ in progress]
    assert stages[0] == "moving" and stages[-1] == "settling"
    fractions = [f for _, _, f, _, _ in progress]
    assert fractions[-1] == 1.0 and all(0.0 <= f <= 1.0 for f in fractions)
    assert progress[-1][-1] == 0.0  # eta


@pytest.mark.timeout(60)
def test_multi_turn_gear_ratio_and_zero_offset(sim):
    with Turntable(fast(sim, velocity_limit_rad_s=2.3, gear_ratio=2.0, zero_offset_rad=0.3)) as table:
        shaft0 = sim.control.state()["position_rad"]
        plate0 = table.angle()
        assert plate0 == pytest.approx(shaft0 / 2 - 0.3, abs=1e-3)
        table.rotate_to(plate0 + 1.25 * math.pi)  # 1.25 servo turns: past the single-turn range
        assert sim.control.state()["position_rad"] == pytest.approx(shaft0 + 2.5 * math.pi, abs=0.003)
        assert table.angle() == pytest.approx(plate0 + 1.25 * math.pi, abs=0.002)


@pytest.mark.timeout(60)
def test_rotate_by_steps_do_not_drift(sim):
    with Turntable(fast(sim, settle_time_s=0.02)) as table:
        start = table.angle()
        for _ in range(6):
            table.rotate_by(math.radians(10))
        assert table.angle() == pytest.approx(start + math.radians(60), abs=0.002)


@pytest.mark.timeout(60)
def test_angle_is_readable_from_another_thread_during_a_move(sim):
    readings, errors, done = [], [], threading.Event()

    def reader(table):
        while not done.is_set():
            try:
                readings.append(table.angle())
            except Exception as exc:  # collected and asserted below
                errors.append(exc)
            time.sleep(0.002)

    with Turntable(fast(sim)) as table:
        start = table.angle()
        thread = threading.Thread(target=reader, args=(table,))
        thread.start()
        table.rotate_to(start + 1.0)
        done.set()
        thread.join()
    assert not errors
    assert len(readings) > 50
    assert all(start - 1e-3 <= r <= start + 1.0 + 1e-3 for r in readings)
    assert readings == sorted(readings) or max(readings) - readings[-1] < 1e-3


@pytest.mark.timeout(60)
def test_cancel_stops_the_plate(sim):
    cancel = threading.Event()
    with Turntable(fast(sim, velocity_limit_rad_s=2.0)) as table:
        start = table.angle()
        threading.Timer(0.3, cancel.set).start()
        with pytest.raises(Cancelled):
            table.rotate_to(start + 2 * math.pi, cancel=cancel)
        time.sleep(0.4)  # braking from 2 rad/s at 20 rad/s^2 takes 0.1 s
        first = sim.control.state()
        time.sleep(0.2)
        second = sim.control.state()
        assert not second["moving"] and second["torque"]
        assert second["position_rad"] == pytest.approx(first["position_rad"], abs=1e-9)
        assert start + 0.2 < second["plate_rad"] < start + 1.5
        assert table.rotate_to(start) == pytest.approx(start, abs=0.002)  # usable afterwards


@pytest.mark.timeout(60)
def test_no_reply_raises_servo_not_responding(sim):
    with Turntable(fast(sim, retries=1)) as table:
        sim.control.fault("no_reply")
        with pytest.raises(ServoNotResponding) as info:
            table.angle()
        assert "did not answer" in str(info.value) and "\n" not in str(info.value)
        sim.control.fault("none")
        table.angle()


@pytest.mark.timeout(60)
def test_bad_crc_is_retried_then_raises(sim):
    with Turntable(fast(sim, retries=2)) as table:
        before = sim.control.state()["rx_packets"]
        sim.control.fault("bad_crc")
        with pytest.raises(ServoCommError) as info:
            table.angle()
        assert type(info.value) is ServoCommError and "CRC" in str(info.value)
        assert sim.control.state()["rx_packets"] - before == 3  # one try + two retries
        sim.control.fault("none")
        table.angle()


@pytest.mark.timeout(60)
def test_overload_during_a_move_then_reboot(sim):
    with Turntable(fast(sim, velocity_limit_rad_s=1.0)) as table:
        start = table.angle()
        threading.Timer(0.4, sim.control.fault, args=("overload",)).start()
        with pytest.raises(ServoHardwareError) as info:
            table.rotate_to(start - 3.0)  # backwards: the raw position goes negative
        assert "overload" in info.value.message and "reboot" in info.value.hint
        assert not sim.control.state()["torque"]
        stopped = table.angle()  # still readable
        assert stopped < start - 0.1
        table.reboot()  # the servo forgets its turn count; the driver keeps the angle continuous
        assert table.hardware_error() == 0
        assert table.angle() == pytest.approx(stopped, abs=1e-3)
        assert sim.control.state()["torque"]
        assert table.rotate_to(start) == pytest.approx(start, abs=0.002)


@pytest.mark.timeout(60)
def test_open_with_a_latched_overload_then_reboot(sim):
    sim.control.fault("overload")
    table = Turntable(fast(sim))
    with pytest.raises(ServoHardwareError) as info:
        table.open()
    assert "overload" in str(info.value) and not table.is_open
    table.reboot()
    assert table.is_open and table.hardware_error() == 0 and sim.control.state()["torque"]
    table.close()


@pytest.mark.timeout(60)
def test_disconnect_during_a_move_reconnects_and_completes(sim, caplog):
    caplog.set_level(logging.INFO, logger="n2d_capture.turntable")
    with Turntable(fast(sim, velocity_limit_rad_s=1.5, reconnect_attempts=10)) as table:
        start = table.angle()
        threading.Timer(0.3, sim.control.disconnect).start()
        threading.Timer(0.9, sim.control.reconnect).start()
        reached = table.rotate_to(start + 2.0)
        assert reached == pytest.approx(start + 2.0, abs=0.002)
        assert sim.control.state()["plate_rad"] == pytest.approx(start + 2.0, abs=0.002)
    assert any("reconnected" in r.getMessage() for r in caplog.records)


@pytest.mark.timeout(60)
def test_disconnect_for_good_raises_servo_disconnected(sim):
    with Turntable(fast(sim, reconnect_attempts=2)) as table:
        sim.control.disconnect()
        with pytest.raises(ServoDisconnected) as info:
            table.angle()
        assert "could not reconnect in 2 attempts" in info.value.message
        assert "\n" not in str(info.value) and "USB" in info.value.hint


@pytest.mark.timeout(60)
def test_a_plate_that_does_not_move_times_out(sim):
    with Turntable(fast(sim, move_timeout_s=0.3)) as table:
        start = table.angle()
        other = PortHandler(sim.link)  # someone else turns the torque off behind the driver's back
        assert other.setBaudRate(57600)
        assert PacketHandler(2.0).write1ByteTxRx(other, 1, 64, 0) == (COMM_SUCCESS, 0)
        other.closePort()
        with pytest.raises(MoveTimeout) as info:
            table.rotate_to(start + 0.5)
        assert "did not settle" in info.value.message and "\n" not in str(info.value)


@pytest.mark.timeout(30)
def test_wrong_port_is_one_clear_line(tmp_path):
    table = Turntable(TurntableConfig(port=str(tmp_path / "ttyUSB9")))
    with pytest.raises(DeviceError) as info:
        table.open()
    text = str(info.value)
    assert text.startswith(f"cannot open serial port {tmp_path / 'ttyUSB9'}: No such file or directory")
    assert "\n" not in text and "ls /dev/ttyUSB" in info.value.hint
    table.close()
    table.close()


@pytest.mark.timeout(60)
def test_unanswered_servo_id_names_what_was_tried(sim):
    with pytest.raises(ServoNotResponding) as info:
        Turntable(fast(sim, servo_id=7, retries=0)).open()
    message = info.value.message
    assert "servo id 7 does not answer" in message and "57600 baud, protocol 2.0" in message
    assert "ids answering at this baud rate: [1]" in message and "\n" not in str(info.value)


@pytest.mark.timeout(60)
def test_protocol_1_servo_not_found(sim):
    with pytest.raises(ServoNotResponding) as info:
        Turntable(fast(sim, protocol=1.0, retries=0)).open()
    assert "protocol 1.0" in info.value.message


def test_config_validation():
    for bad in (dict(baud=12345), dict(servo_id=300), dict(protocol=3.0), dict(gear_ratio=0.0),
                dict(velocity_limit_rad_s=-1.0), dict(retries=-1), dict(port="")):
        with pytest.raises(ValueError):
            TurntableConfig(**bad)
    with pytest.raises(ConfigError):
        from_dict(TurntableConfig, {"baud": 1234})
    assert from_dict(TurntableConfig, {"port": "/dev/ttyACM0", "gear_ratio": "3"}).gear_ratio == 3.0


def test_not_open_is_a_clear_error():
    with pytest.raises(DeviceError) as info:
        Turntable(TurntableConfig()).angle()
    assert "not open" in info.value.message
