"""The Go1 low-level wire format: sizes, offsets, fixed-point encodings, CRC — against docs/go1-sdk.md and, when the
optional ``unitree_legged_sdk`` wheel is installed, against the real SDK over 127.0.0.1."""

import socket
import time

import numpy as np
import pytest

from cpgjax.robot import wire


def _reference_crc(data: bytes) -> int:
    """docs/go1-sdk.md §1.4 literally: MSB-first CRC-32/0x04C11DB7 over little-endian uint32 words, bit by bit."""
    crc = 0xFFFFFFFF
    for word in np.frombuffer(data, "<u4").tolist():
        for bit in range(31, -1, -1):
            top = (crc >> 31) ^ ((word >> bit) & 1)
            crc = (crc << 1) & 0xFFFFFFFF
            if top:
                crc ^= 0x04C11DB7
    return crc


def _state(**overrides) -> wire.RobotState:
    fields = dict(
        tick_ms=1234,
        quaternion_wxyz=np.array([0.9, 0.1, 0.2, 0.3]),
        gyro_rad_s=np.array([1.0, 2.0, 3.0]),
        accel_mps2=np.array([0.0, 0.0, 9.8]),
        rpy_rad=np.array([0.1, 0.2, 0.3]),
        motor_mode=np.full(12, wire.MODE_SERVO, np.uint8),
        q_rad=np.linspace(-1, 1, 12),
        dq_rad_s=np.linspace(2, -2, 12),
        tau_est_nm=np.linspace(-20, 20, 12),
        motor_temperature_c=np.arange(12) + 30,
        foot_force_raw=np.array([10, -20, 300, 4000]),
        wireless_remote=wire.remote_with_buttons("L2", "B"),
    )
    fields.update(overrides)
    return wire.RobotState(**fields)


def _command(tau=None, kp=None, kd=None) -> wire.MotorCommand:
    i = np.arange(12)
    return wire.MotorCommand(
        np.full(12, wire.MODE_SERVO, np.uint8),
        0.1 * i,
        -0.2 * i,
        1.7 * i - 10 if tau is None else tau,
        3.3 * i if kp is None else kp,
        0.7 * i if kd is None else kd,
    )


def test_sizes_and_offsets_match_the_sdk_wire_layout():
    assert wire.LOW_CMD_DTYPE.itemsize == 614 and wire.LOW_STATE_DTYPE.itemsize == 807
    cmd_fields = {name: wire.LOW_CMD_DTYPE.fields[name][1] for name in wire.LOW_CMD_DTYPE.names}
    assert cmd_fields == {
        "head": 0,
        "level_flag": 2,
        "frame_reserve": 3,
        "sn": 4,
        "version": 12,
        "bandwidth": 20,
        "motor": 22,
        "bms": 562,
        "wireless_remote": 566,
        "reserve": 606,
        "crc": 610,
    }
    state_fields = {name: wire.LOW_STATE_DTYPE.fields[name][1] for name in wire.LOW_STATE_DTYPE.names}
    assert state_fields["imu"] == 22 and state_fields["motor"] == 75 and state_fields["bms"] == 715
    assert state_fields["foot_force"] == 739 and state_fields["tick"] == 755
    assert state_fields["wireless_remote"] == 759 and state_fields["crc"] == 803
    motor = wire.LOW_STATE_DTYPE.fields["motor"][0].base
    assert motor.itemsize == 32 and motor.fields["tau_est"][1] == 11 and motor.fields["temperature"][1] == 23


@pytest.mark.parametrize("length", [608, 800, 124, 4])
def test_crc_equals_the_bitwise_definition(length):
    data = np.random.default_rng(length).integers(0, 256, length, dtype=np.uint8).tobytes()
    assert wire.crc32_words(data) == _reference_crc(data)


def test_low_cmd_fixed_point_encoding_truncates_toward_zero():
    tau = np.array([23.7, -23.7, 0.003, -0.003, 127.99, -128.0, 1.0, 0, 0, 0, 0, 0])
    kp = np.array([0.03, 2047.9, 70.0, 0, 0, 0, 0, 0, 0, 0, 0, 0])
    kd = np.array([0.06, 4095.9, 1.3, 0, 0, 0, 0, 0, 0, 0, 0, 0])
    packet = wire.encode_low_cmd(_command(tau, kp, kd))
    assert len(packet) == 614 and packet[:3] == b"\xfe\xef\xff"
    raw = np.frombuffer(packet, wire.LOW_CMD_DTYPE)[0]["motor"]
    np.testing.assert_array_equal(raw["tau"][:7], [6067, -6067, 0, 0, 32765, -32768, 256])  # trunc(τ·256)
    np.testing.assert_array_equal(raw["kp"][:3], [0, 65532, 2240])  # trunc(Kp·32): 0.03·32 = 0.96 → 0
    np.testing.assert_array_equal(raw["kd"][:3], [0, 65534, 20])  # trunc(Kd·16)
    # Unused slots as the SDK's InitCmdData leaves them.
    assert raw["mode"][19] == wire.MODE_SERVO and raw["q"][19] == np.float32(wire.POS_STOP_F)
    assert int.from_bytes(packet[610:], "little") == _reference_crc(packet[:608])


@pytest.mark.parametrize(
    "field, value",
    [
        ("tau", 128.0),
        ("tau", -128.5),
        ("tau", np.nan),
        ("kp", -1.0),
        ("kp", 2048.0),
        ("kd", -0.1),
        ("kd", 4096.0),
        ("kd", np.inf),
    ],
)
def test_values_the_wire_would_wrap_are_refused(field, value):
    values = {"tau": np.zeros(12), "kp": np.zeros(12), "kd": np.zeros(12)}
    values[field][5] = value
    with pytest.raises(wire.ProtocolError, match="not encodable"):
        wire.encode_low_cmd(_command(**values))


def test_non_finite_position_target_is_refused():
    cmd = _command()._replace(q_rad=np.where(np.arange(12) == 3, np.nan, 0.0))
    with pytest.raises(wire.ProtocolError, match="not finite"):
        wire.encode_low_cmd(cmd)


def test_low_cmd_round_trip():
    cmd = _command()
    back = wire.decode_low_cmd(wire.encode_low_cmd(cmd))
    np.testing.assert_allclose(back.tau_nm, cmd.tau_nm, atol=1 / 256)
    np.testing.assert_allclose(back.kp_nm_rad, cmd.kp_nm_rad, atol=1 / 32)
    np.testing.assert_allclose(back.kd_nm_s_rad, cmd.kd_nm_s_rad, atol=1 / 16)
    np.testing.assert_allclose(back.q_rad, cmd.q_rad, rtol=1e-6)


def test_low_state_round_trip_and_encodings():
    state = _state()
    packet = wire.encode_low_state(state)
    assert len(packet) == 807
    raw = np.frombuffer(packet, wire.LOW_STATE_DTYPE)[0]
    np.testing.assert_array_equal(raw["motor"]["tau_est"][:12], np.round(state.tau_est_nm * 256))
    back = wire.decode_low_state(packet)
    assert back.tick_ms == 1234 and back.wireless_remote == state.wireless_remote
    np.testing.assert_array_equal(back.foot_force_raw, state.foot_force_raw)
    np.testing.assert_array_equal(back.motor_temperature_c, state.motor_temperature_c)
    np.testing.assert_allclose(back.q_rad, state.q_rad, rtol=1e-6)
    np.testing.assert_allclose(back.tau_est_nm, state.tau_est_nm, atol=1 / 512)
    assert wire.remote_buttons(back.wireless_remote) == (wire.REMOTE_BUTTON_BITS["L2"] | wire.REMOTE_BUTTON_BITS["B"])


@pytest.mark.parametrize(
    "damage, match",
    [
        (lambda p: p[:-4] + bytes(4), "crc"),
        (lambda p: b"\x00\x00" + p[2:], "head"),
        (lambda p: p[:2] + b"\xee" + p[3:], "level"),
        (lambda p: p[:-1], "bytes"),
    ],
)
def test_invalid_state_datagrams_are_rejected(damage, match):
    with pytest.raises(wire.ProtocolError, match=match):
        wire.decode_low_state(damage(wire.encode_low_state(_state())))


def test_fault_injection_helpers_break_exactly_one_thing():
    with pytest.raises(wire.ProtocolError, match="crc"):
        wire.decode_low_state(wire.encode_low_state(_state(), corrupt_crc=True))
    with pytest.raises(wire.ProtocolError, match="head"):
        wire.decode_low_state(wire.encode_low_state(_state(), head=(0, 0)))


# ------------------------------------------------------------------------------------ against the real SDK wheel


@pytest.fixture
def sdk_pair():
    """The SDK's UDP on 127.0.0.1 ephemeral ports and a fake robot socket bound to its target port."""
    sdk = pytest.importorskip("unitree_legged_sdk.robot_interface")
    robot = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    robot.bind(("127.0.0.1", 0))
    robot.settimeout(2.0)
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    local_port = probe.getsockname()[1]
    probe.close()
    udp = sdk.UDP(wire.LEVEL_LOW, local_port, "127.0.0.1", robot.getsockname()[1])
    yield sdk, udp, robot
    del udp
    robot.close()


def test_the_sdk_sends_what_we_decode_and_we_encode_what_it_sends(sdk_pair):
    sdk, udp, robot = sdk_pair
    cmd = sdk.LowCmd()
    udp.InitCmdData(cmd)
    ours = _command()
    motors = cmd.motorCmd
    for i in range(12):
        motors[i].q, motors[i].dq = float(ours.q_rad[i]), float(ours.dq_rad_s[i])
        motors[i].tau, motors[i].Kp, motors[i].Kd = (
            float(ours.tau_nm[i]),
            float(ours.kp_nm_rad[i]),
            float(ours.kd_nm_s_rad[i]),
        )
    udp.SetSend(cmd)
    udp.Send()
    packet, _ = robot.recvfrom(2048)
    assert packet == wire.encode_low_cmd(ours)  # byte for byte, CRC included


def test_the_sdk_accepts_our_state_and_rejects_our_faults(sdk_pair):
    sdk, udp, robot = sdk_pair
    cmd, state = sdk.LowCmd(), sdk.LowState()
    udp.InitCmdData(cmd)
    udp.SetSend(cmd)
    udp.Send()
    _, client = robot.recvfrom(2048)

    def deliver(packet: bytes) -> int:
        robot.sendto(packet, client)
        time.sleep(0.02)
        return udp.Recv()

    ours = _state()
    assert deliver(wire.encode_low_state(ours)) == 0
    udp.GetRecv(state)
    assert state.tick == 1234 and list(state.footForce) == [10, -20, 300, 4000]
    np.testing.assert_allclose([state.motorState[i].tauEst for i in range(12)], ours.tau_est_nm, atol=1 / 256)
    np.testing.assert_allclose(list(state.imu.quaternion), ours.quaternion_wxyz, rtol=1e-6)
    assert state.motorState[11].temperature == 41
    assert deliver(wire.encode_low_state(ours._replace(tick_ms=7), corrupt_crc=True)) == -3
    assert deliver(wire.encode_low_state(ours._replace(tick_ms=8), head=(0, 0))) == -1
    udp.GetRecv(state)
    assert state.tick == 1234  # neither fault reached the state
