"""Kinematics of the 5-joint welding arm: DH forward kinematics, closed-form IK round trips."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from chcos.apps.weld.kinematics import Arm, UnreachableError, matmul, translation, wrap_angle
from chcos.errors import ChcosError, ConfigError

ARM = Arm()


def _angle_diff(a: float, b: float) -> float:
    return abs(wrap_angle(a - b))


def test_zero_pose_is_arm_stretched_out_with_torch_down() -> None:
    pose = ARM.tool_pose((0.0, 0.0, 0.0, 0.0, 0.0))
    assert pose.position == pytest.approx((850.0, 0.0, 250.0), abs=1e-9)
    assert pose.z_axis == pytest.approx((0.0, 0.0, -1.0), abs=1e-12)
    assert pose.tilt == pytest.approx(0.0, abs=1e-9)
    assert pose.yaw == pytest.approx(0.0, abs=1e-12)


def test_base_yaw_rotates_tip_about_vertical_axis() -> None:
    pose = ARM.tool_pose((math.pi / 2, 0.0, 0.0, 0.0, 0.0))
    assert pose.position == pytest.approx((0.0, 850.0, 250.0), abs=1e-9)
    # tool yaw = theta1 - theta5
    assert ARM.tool_pose((0.3, 0.0, 0.0, 0.0, 0.5)).yaw == pytest.approx(-0.2)


def test_shoulder_up_raises_the_tip_and_tilts_the_torch() -> None:
    pose = ARM.tool_pose((0.0, math.pi / 2, 0.0, 0.0, 0.0))
    # upper arm and forearm vertical: wrist at 400 + 850 mm, torch points along -x... i.e. tilted
    assert pose.position[2] == pytest.approx(1250.0, abs=1e-9)
    assert pose.tilt == pytest.approx(math.pi / 2, abs=1e-9)


joint_vectors = st.tuples(
    *(
        st.floats(lo, hi)
        for lo, hi in ((-2.9, 2.9), (-1.0, 2.6), (-2.8, 2.8), (-2.9, 2.9), (-3.1, 3.1))
    )
)


@given(joint_vectors)
def test_t5_is_a_rigid_transform(q: tuple[float, float, float, float, float]) -> None:
    t5 = ARM.forward(q)
    rot = [row[:3] for row in t5[:3]]
    for i in range(3):
        for j in range(3):
            dot = sum(rot[i][k] * rot[j][k] for k in range(3))
            assert dot == pytest.approx(1.0 if i == j else 0.0, abs=1e-9)
    assert t5[3] == (0.0, 0.0, 0.0, 1.0)
    frames = ARM.frames(q)
    assert len(frames) == 5 and frames[-1] == t5
    # the torch is d5 = 150 mm along T5's z axis from the wrist centre (origin of T4)
    wrist = translation(frames[3])
    tip = translation(t5)
    z = (t5[0][2], t5[1][2], t5[2][2])
    for k in range(3):
        assert tip[k] == pytest.approx(wrist[k] + 150.0 * z[k], abs=1e-9)


workspace = st.tuples(
    st.floats(220.0, 770.0),  # horizontal distance of the tip from the base axis, mm
    st.floats(-2.8, 2.8),  # azimuth, rad
    st.floats(-50.0, 300.0),  # tip height, mm
    st.floats(-math.pi, math.pi),  # tool yaw, rad
)


@settings(max_examples=300)
@given(workspace)
def test_fk_of_ik_returns_the_requested_pose(p: tuple[float, float, float, float]) -> None:
    r, az, z, yaw = p
    target = (r * math.cos(az), r * math.sin(az), z)
    q = ARM.inverse_down(target, yaw)
    assert ARM.within_limits(q)
    pose = ARM.tool_pose(q)
    assert pose.position == pytest.approx(target, abs=1e-6)
    assert pose.tilt == pytest.approx(0.0, abs=1e-6)
    assert _angle_diff(pose.yaw, yaw) < 1e-9


@given(workspace)
def test_ik_of_fk_returns_the_joints(p: tuple[float, float, float, float]) -> None:
    r, az, z, yaw = p
    q = ARM.inverse_down((r * math.cos(az), r * math.sin(az), z), yaw)
    again = ARM.inverse_down(translation(ARM.forward(q)), ARM.tool_pose(q).yaw)
    for a, b in zip(q, again, strict=True):
        assert _angle_diff(a, b) < 1e-9


def test_ik_is_elbow_up() -> None:
    q = ARM.inverse_down((550.0, -150.0, 10.0), math.pi / 2)
    assert q[2] < 0.0
    elbow = translation(ARM.frames(q)[1])
    wrist = translation(ARM.frames(q)[3])
    assert elbow[2] > wrist[2]


@pytest.mark.parametrize(
    ("position", "fragment"),
    [
        ((1200.0, 0.0, 0.0), "beyond the reach"),
        ((0.0, 0.0, 100.0), "above the base axis"),
        ((-600.0, 1e-3, 50.0), "joint 1"),
        ((20.0, 0.0, 260.0), "closer than"),
    ],
)
def test_unreachable_positions_raise(position: tuple[float, float, float], fragment: str) -> None:
    with pytest.raises(UnreachableError, match=fragment) as info:
        ARM.inverse_down(position, 0.0)
    assert isinstance(info.value, ChcosError)
    assert "tip position" in str(info.value)


def test_bad_geometry_and_joint_vectors_are_config_errors() -> None:
    with pytest.raises(ConfigError, match="forearm"):
        Arm(forearm=-1.0)
    with pytest.raises(ConfigError, match="5 angles"):
        ARM.forward((0.0, 0.0, 0.0))
    with pytest.raises(ConfigError, match="lower < upper"):
        Arm(limits=[(0.0, 1.0)] * 4 + [(1.0, 0.0)])


def test_matmul_identity_and_wrap_angle() -> None:
    t = ARM.forward((0.1, 0.2, -0.3, 0.4, 0.5))
    ident = ARM.forward((0.0,) * 5)
    assert matmul(t, ((1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 1))) == t
    assert matmul(ident, ident) != ident
    assert wrap_angle(3 * math.pi) == pytest.approx(math.pi)
    assert wrap_angle(-math.pi) == pytest.approx(math.pi)
    assert wrap_angle(0.5) == pytest.approx(0.5)
