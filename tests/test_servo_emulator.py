"""The XM430-W350 emulator, driven by the real dynamixel_sdk over a pty from another process."""

from __future__ import annotations

import math
import termios
import time
from pathlib import Path

import pytest
from dynamixel_sdk import (
    COMM_RX_CORRUPT,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    GroupBulkRead,
    GroupSyncRead,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)

from n2d_sim.servo import PtyServo, ServoEmulator, crc16, make_packet, plan_move

# Control-table addresses of the X-series (written out here on purpose, not imported).
MODEL_NUMBER, ID, OPERATING_MODE, HOMING_OFFSET, MAX_POSITION_LIMIT = 0, 7, 11, 20, 48
TORQUE, LED, HW_ERROR = 64, 65, 70
GOAL_VELOCITY, PROFILE_ACC, PROFILE_VEL, GOAL_POSITION = 104, 108, 112, 116
MOVING, PRESENT_VELOCITY, PRESENT_POSITION = 122, 128, 132
ERR_CRC, ERR_DATA_RANGE, ERR_DATA_LIMIT, ERR_ACCESS, ALERT = 3, 4, 6, 7, 0x80


@pytest.fixture
def bus(sim):
    """(PortHandler, PacketHandler) of the real SDK on the emulator's port."""
    port = PortHandler(sim.link)
    assert port.setBaudRate(57600)
    yield port, PacketHandler(2.0)
    if port.is_open:
        port.closePort()


def call(fn, *args):
    """An SDK call, tried again when the reply timed out (the SDK waits only ~34 ms; CI machines can be busy)."""
    for _ in range(3):
        reply = fn(*args)
        if (reply[-2] if isinstance(reply, tuple) else reply) != COMM_RX_TIMEOUT:
            break
    return reply


def ok(fn, *args):
    """Call `fn(*args)` (an SDK call), assert success; returns the value (or None)."""
    *value, result, error = call(fn, *args)
    assert result == COMM_SUCCESS, f"comm result {result}"
    assert error == 0, f"status error {error}"
    return value[0] if value else None


def signed32(value: int) -> int:
    return value - (1 << 32) if value & (1 << 31) else value


def wait_until_still(port, ph, timeout_s: float = 10.0, sid: int = 1) -> tuple[float, bool]:
    """Poll MOVING until 0; returns (elapsed s, whether it was seen 1)."""
    t0, seen = time.monotonic(), False
    while time.monotonic() - t0 < timeout_s:
        moving = ok(ph.read1ByteTxRx, port, sid, MOVING)
        seen |= bool(moving)
        if not moving:
            return time.monotonic() - t0, seen
        time.sleep(0.005)
    raise AssertionError("servo still moving")


# ---------------------------------------------------------------- pure emulator (no I/O)

def test_crc_matches_the_sdk():
    ph = PacketHandler(2.0)
    for data in (b"", b"\xff\xff\xfd\x00\x01\x03\x00\x01", bytes(range(256)), b"n2d" * 50):
        assert crc16(data) == ph.updateCRC(0, list(data), len(data))


def test_split_packets_and_garbage_resync():
    emu = ServoEmulator(servo_id=3)
    ping = make_packet(3, b"\x01")
    assert emu.handle_bytes(b"\x00\xff\x12\xff\xff\xfd" + ping[:5]) == b""  # noise, then half a packet
    reply = emu.handle_bytes(ping[5:])
    assert reply[:5] == b"\xff\xff\xfd\x00\x03" and reply[7:9] == b"\x55\x00"
    assert int.from_bytes(reply[9:11], "little") == 1020
    assert crc16(reply[:-2]) == int.from_bytes(reply[-2:], "little")
    other = make_packet(4, b"\x01")  # another servo on the bus: silence
    assert emu.handle_bytes(other) == b""


def test_motion_profile_with_a_fake_clock():
    now = [0.0]
    emu = ServoEmulator(clock=lambda: now[0])
    write = lambda addr, value, size: emu.handle_bytes(  # noqa: E731
        make_packet(1, bytes([3, addr, 0]) + (value & (1 << 8 * size) - 1).to_bytes(size, "little")))
    write(OPERATING_MODE, 4, 1)
    write(PROFILE_ACC, 50, 4)
    write(PROFILE_VEL, 100, 4)
    write(TORQUE, 1, 1)
    write(GOAL_POSITION, 4096, 4)
    v = 100 * 0.229 / 60 * 4096
    a = 50 * 214.577 / 3600 * 4096
    expected = 4096 / v + v / a
    now[0] = expected / 2
    assert emu.read_field("moving") == 1
    assert emu.read_field("present_velocity") == 100  # cruising
    now[0] = expected + 1e-6
    assert emu.read_field("moving") == 0
    assert emu.read_field("present_position") == 4096
    assert emu.shaft_angle_rad() == pytest.approx(2 * math.pi)
    total = sum(d for d, _, _ in plan_move(0, 0, 4096, v, a))
    assert total == pytest.approx(expected)


def test_new_goal_while_moving_is_continuous():
    now = [0.0]
    emu = ServoEmulator(clock=lambda: now[0])
    for addr, value, size in ((OPERATING_MODE, 4, 1), (PROFILE_ACC, 20, 4), (PROFILE_VEL, 150, 4),
                              (TORQUE, 1, 1), (GOAL_POSITION, 8000, 4)):
        emu.handle_bytes(make_packet(1, bytes([3, addr, 0]) + value.to_bytes(size, "little")))
    now[0] = 0.5
    before = emu.shaft_angle_rad()
    emu.handle_bytes(make_packet(1, bytes([3, GOAL_POSITION, 0]) + (0).to_bytes(4, "little")))  # reverse
    assert emu.shaft_angle_rad() == pytest.approx(before)
    now[0] = 0.51
    assert emu.shaft_angle_rad() > before  # still braking forward: no jump, no instant reversal
    now[0] = 20.0
    assert emu.read_field("present_position") == 0 and emu.read_field("moving") == 0


@pytest.mark.timeout(60)
def test_in_process_pty_servo(tmp_path):
    """The sim node's way: emulator thread and SDK in one process; the true angle read directly."""
    with PtyServo(ServoEmulator(servo_id=5, gear_ratio=2.0), link=tmp_path / "ttyDXL") as servo:
        assert Path(servo.port).resolve() == Path(servo.tty)
        port, ph = PortHandler(servo.port), PacketHandler(2.0)
        assert port.setBaudRate(1000000)
        assert ok(ph.ping, port, 5) == 1020
        ok(ph.write1ByteTxRx, port, 5, OPERATING_MODE, 4)
        ok(ph.write4ByteTxRx, port, 5, PROFILE_VEL, 200)
        ok(ph.write1ByteTxRx, port, 5, TORQUE, 1)
        ok(ph.write4ByteTxRx, port, 5, GOAL_POSITION, 2048)
        wait_until_still(port, ph, sid=5)
        assert servo.emulator.shaft_angle_rad() == pytest.approx(math.pi)
        assert servo.emulator.plate_angle_rad() == pytest.approx(math.pi / 2)
        port.closePort()
    assert not (tmp_path / "ttyDXL").exists()


# ---------------------------------------------------------------- over the pty, another process

@pytest.mark.timeout(60)
def test_ping_reports_xm430_w350(sim, bus):
    port, ph = bus
    assert ok(ph.ping, port, 1) == 1020
    assert ok(ph.read2ByteTxRx, port, 1, MODEL_NUMBER) == 1020
    found, result = ph.broadcastPing(port)
    assert result == COMM_SUCCESS and list(found) == [1] and found[1][0] == 1020
    _, result, _ = ph.ping(port, 2)
    assert result == COMM_RX_TIMEOUT


@pytest.mark.timeout(60)
def test_read_write_round_trip(sim, bus):
    port, ph = bus
    ok(ph.write1ByteTxRx, port, 1, LED, 1)
    assert ok(ph.read1ByteTxRx, port, 1, LED) == 1
    ok(ph.write4ByteTxRx, port, 1, PROFILE_VEL, 123)
    assert ok(ph.read4ByteTxRx, port, 1, PROFILE_VEL) == 123
    ok(ph.write4ByteTxRx, port, 1, HOMING_OFFSET, -1000 & 0xFFFFFFFF)  # EEPROM, torque off: allowed
    assert signed32(ok(ph.read4ByteTxRx, port, 1, HOMING_OFFSET)) == -1000
    # One write spanning two fields, one read back.
    ok(ph.writeTxRx, port, 1, PROFILE_ACC, 8, [7, 0, 0, 0, 200, 0, 0, 0])
    assert ok(ph.readTxRx, port, 1, PROFILE_ACC, 8) == [7, 0, 0, 0, 200, 0, 0, 0]


@pytest.mark.timeout(60)
def test_rejected_writes(sim, bus):
    port, ph = bus
    assert call(ph.write4ByteTxRx, port, 1, PRESENT_POSITION, 5) == (COMM_SUCCESS, ERR_ACCESS)  # read-only
    assert call(ph.write1ByteTxRx, port, 1, 14, 5) == (COMM_SUCCESS, ERR_ACCESS)  # no such field
    assert call(ph.write1ByteTxRx, port, 1, LED, 2) == (COMM_SUCCESS, ERR_DATA_RANGE)
    assert call(ph.write1ByteTxRx, port, 1, OPERATING_MODE, 2) == (COMM_SUCCESS, ERR_DATA_RANGE)
    assert ok(ph.read1ByteTxRx, port, 1, LED) == 0


@pytest.mark.timeout(60)
def test_eeprom_write_with_torque_on_is_an_access_error(sim, bus):
    port, ph = bus
    ok(ph.write1ByteTxRx, port, 1, TORQUE, 1)
    assert call(ph.write1ByteTxRx, port, 1, OPERATING_MODE, 4) == (COMM_SUCCESS, ERR_ACCESS)
    assert ok(ph.read1ByteTxRx, port, 1, OPERATING_MODE) == 3
    ok(ph.write1ByteTxRx, port, 1, TORQUE, 0)
    ok(ph.write1ByteTxRx, port, 1, OPERATING_MODE, 4)
    assert ok(ph.read1ByteTxRx, port, 1, OPERATING_MODE) == 4


@pytest.mark.timeout(60)
def test_bad_crc_request_gets_a_crc_error(sim, bus):
    port, ph = bus
    packet = [0xFF, 0xFF, 0xFD, 0x00, 1, 7, 0, 0x02, LED, 0, 1, 0]  # READ LED, 1 byte
    crc = ph.updateCRC(0, packet, len(packet)) ^ 0x1234
    port.clearPort()
    port.writePort(packet + [crc & 0xFF, crc >> 8])
    port.setPacketTimeoutMillis(1000)
    reply, result = ph.rxPacket(port, False)
    assert result == COMM_SUCCESS and reply[7] == 0x55 and reply[8] == ERR_CRC
    assert sim.control.state()["crc_errors"] == 1
    assert ok(ph.ping, port, 1) == 1020  # and it still listens


@pytest.mark.timeout(60)
def test_byte_stuffing_round_trip(sim, bus):
    port, ph = bus
    goal = -131073  # little-endian FF FF FD FF: both the request and the reply need stuffing
    assert (goal & 0xFFFFFFFF).to_bytes(4, "little")[:3] == b"\xff\xff\xfd"
    ok(ph.write1ByteTxRx, port, 1, OPERATING_MODE, 4)
    ok(ph.write4ByteTxRx, port, 1, GOAL_POSITION, goal & 0xFFFFFFFF)
    assert signed32(ok(ph.read4ByteTxRx, port, 1, GOAL_POSITION)) == goal
    assert sim.control.state()["goal_position"] == goal
    # The raw status packet on the wire carries the stuffed FF FF FD FD.
    assert ph.readTx(port, 1, GOAL_POSITION, 4) == COMM_SUCCESS
    raw = b""
    deadline = time.monotonic() + 1
    while len(raw) < 16 and time.monotonic() < deadline:
        raw += bytes(port.readPort(64))
    port.is_using = False
    assert b"\xff\xff\xfd\xfd" in raw[7:]
    assert int.from_bytes(raw[5:7], "little") == len(raw) - 7 == 9  # 0x55, error, 4+1 data, CRC
    assert crc16(raw[:-2]) == int.from_bytes(raw[-2:], "little")


@pytest.mark.timeout(60)
def test_rotation_follows_the_profile_in_wall_clock_time(sim, bus):
    port, ph = bus
    ok(ph.write1ByteTxRx, port, 1, OPERATING_MODE, 4)
    ok(ph.write4ByteTxRx, port, 1, PROFILE_ACC, 50)
    ok(ph.write4ByteTxRx, port, 1, PROFILE_VEL, 100)
    ok(ph.write1ByteTxRx, port, 1, TORQUE, 1)
    start = signed32(ok(ph.read4ByteTxRx, port, 1, PRESENT_POSITION))
    v, a = 100 * 0.229 / 60 * 4096, 50 * 214.577 / 3600 * 4096
    expected = 1024 / v + v / a  # 90 degrees: accelerate, cruise, decelerate (~0.78 s)
    ok(ph.write4ByteTxRx, port, 1, GOAL_POSITION, start + 1024)
    elapsed, seen_moving = wait_until_still(port, ph)
    assert seen_moving
    assert 0.7 * expected < elapsed < 1.3 * expected
    assert signed32(ok(ph.read4ByteTxRx, port, 1, PRESENT_POSITION)) == start + 1024
    state = sim.control.state()
    assert state["position_rad"] == pytest.approx((start + 1024) / 4096 * 2 * math.pi, abs=1e-9)
    assert not state["moving"]


@pytest.mark.timeout(60)
def test_position_mode_clamps_to_the_limits(sim, bus):
    port, ph = bus
    ok(ph.write4ByteTxRx, port, 1, MAX_POSITION_LIMIT, 3000)
    ok(ph.write1ByteTxRx, port, 1, TORQUE, 1)
    ok(ph.write4ByteTxRx, port, 1, GOAL_POSITION, 4000)
    assert ok(ph.read4ByteTxRx, port, 1, GOAL_POSITION) == 3000
    wait_until_still(port, ph)
    assert ok(ph.read4ByteTxRx, port, 1, PRESENT_POSITION) == 3000


@pytest.mark.timeout(60)
def test_velocity_mode_integrates_goal_velocity(sim, bus):
    port, ph = bus
    ok(ph.write1ByteTxRx, port, 1, OPERATING_MODE, 1)
    ok(ph.write1ByteTxRx, port, 1, TORQUE, 1)
    start = sim.control.state()["position_rad"]
    ok(ph.write4ByteTxRx, port, 1, GOAL_VELOCITY, 50)
    time.sleep(0.5)
    assert ok(ph.read1ByteTxRx, port, 1, MOVING) == 1
    assert signed32(ok(ph.read4ByteTxRx, port, 1, PRESENT_VELOCITY)) == 50
    travelled = sim.control.state()["position_rad"] - start
    assert travelled == pytest.approx(0.5 * 50 * 0.229 * 2 * math.pi / 60, rel=0.3)
    assert call(ph.write4ByteTxRx, port, 1, GOAL_VELOCITY, 500) == (COMM_SUCCESS, ERR_DATA_LIMIT)  # limit is 200
    ok(ph.write4ByteTxRx, port, 1, GOAL_VELOCITY, 0)
    wait_until_still(port, ph)


@pytest.mark.timeout(60)
def test_sync_bulk_and_registered_writes(sim, bus):
    port, ph = bus
    ok(ph.write1ByteTxRx, port, 1, OPERATING_MODE, 4)
    ok(ph.write1ByteTxRx, port, 1, TORQUE, 1)
    ok(ph.write4ByteTxRx, port, 1, PROFILE_VEL, 200)
    sync_write = GroupSyncWrite(port, ph, GOAL_POSITION, 4)
    assert sync_write.addParam(1, list((512).to_bytes(4, "little")))
    assert sync_write.txPacket() == COMM_SUCCESS
    wait_until_still(port, ph)
    sync_read = GroupSyncRead(port, ph, PRESENT_POSITION, 4)
    assert sync_read.addParam(1)
    assert call(sync_read.txRxPacket) == COMM_SUCCESS
    assert sync_read.getData(1, PRESENT_POSITION, 4) == 512
    bulk_read = GroupBulkRead(port, ph)
    assert bulk_read.addParam(1, GOAL_POSITION, 4)
    assert call(bulk_read.txRxPacket) == COMM_SUCCESS
    assert bulk_read.getData(1, GOAL_POSITION, 4) == 512
    # REG_WRITE waits for ACTION.
    assert call(ph.regWriteTxRx, port, 1, LED, 1, [1]) == (COMM_SUCCESS, 0)
    assert ok(ph.read1ByteTxRx, port, 1, LED) == 0
    assert ph.action(port, 1) == COMM_SUCCESS
    time.sleep(0.05)
    assert ok(ph.read1ByteTxRx, port, 1, LED) == 1


@pytest.mark.timeout(60)
def test_overload_alerts_until_reboot(sim, bus):
    port, ph = bus
    ok(ph.write1ByteTxRx, port, 1, TORQUE, 1)
    sim.control.fault("overload")
    model, result, error = call(ph.ping, port, 1)
    assert result == COMM_SUCCESS and error & ALERT
    value, result, error = call(ph.read1ByteTxRx, port, 1, HW_ERROR)
    assert (value, error) == (0x20, ALERT)
    assert call(ph.read1ByteTxRx, port, 1, TORQUE)[0] == 0
    call(ph.write1ByteTxRx, port, 1, TORQUE, 1)  # refused: only a reboot clears a shutdown
    assert call(ph.read1ByteTxRx, port, 1, TORQUE)[0] == 0
    assert sim.control.state()["hardware_error"] == 0x20
    assert call(ph.reboot, port, 1) == (COMM_SUCCESS, ALERT)  # answers, then reboots
    time.sleep(0.1)
    assert ok(ph.read1ByteTxRx, port, 1, HW_ERROR) == 0
    ok(ph.write1ByteTxRx, port, 1, TORQUE, 1)


@pytest.mark.timeout(60)
def test_no_reply_and_bad_crc_faults(sim, bus):
    port, ph = bus
    sim.control.fault("no_reply")
    assert ph.ping(port, 1)[1] == COMM_RX_TIMEOUT
    sim.control.fault("bad_crc")
    assert ph.ping(port, 1)[1] == COMM_RX_CORRUPT
    sim.control.fault("none")
    assert ok(ph.ping, port, 1) == 1020


@pytest.mark.timeout(60)
def test_disconnect_and_reconnect_keep_the_servo_state(sim, bus):
    port, ph = bus
    ok(ph.write1ByteTxRx, port, 1, LED, 1)
    sim.control.disconnect()
    assert not Path(sim.link).exists()
    with pytest.raises((OSError, termios.error)):  # the pty hung up, like a pulled USB cable
        ph.ping(port, 1)
    port.closePort()
    sim.control.reconnect()
    assert sim.control.state()["connected"]
    port = PortHandler(sim.link)
    assert port.setBaudRate(57600)
    assert ok(ph.read1ByteTxRx, port, 1, LED) == 1  # the servo kept power: same state
    port.closePort()


@pytest.mark.timeout(60)
def test_sigterm_exits_cleanly(sim):
    sim.proc.terminate()
    assert sim.proc.wait(timeout=5) == 0
    assert not Path(sim.link).is_symlink()
    assert not sim.control.path.exists()
