"""kinematics - the 5-joint arc-welding arm: DH table, forward kinematics to T5, inverse kinematics.

The arm of the thesis' reference cell (section 5.1, appendix 2 tasks A4/B4): base yaw, shoulder
pitch, elbow pitch, wrist pitch and wrist (torch) roll. Standard Denavit-Hartenberg convention,
``T(i-1 -> i) = Rz(theta_i) * Tz(d_i) * Tx(a_i) * Rx(alpha_i)``, lengths in mm, angles in rad:

====  ==========  ==============  =============  ========  =====================================
 i    joint       d (mm)          a (mm)         alpha     limits (deg)
====  ==========  ==============  =============  ========  =====================================
 1    base yaw    400 (shoulder)  0              +90 deg   -170 .. 170
 2    shoulder    0               450 (upper)    0         -60 .. 150
 3    elbow       0               400 (forearm)  0         -165 .. 165
 4    wrist pitch 0               0              +90 deg   -170 .. 170
 5    torch roll  150 (torch)     0              0         -180 .. 180
====  ==========  ==============  =============  ========  =====================================

Base frame: z up, origin on the floor under the base axis. Zero pose: upper arm and forearm
horizontal along +x, torch pointing straight down (tool z = -Z), tip at (850, 0, 250) mm. A pitch
angle is positive upwards; the torch points down exactly when ``theta2 + theta3 + theta4 == 0``.
The tool frame T5 has z along the torch (towards the work) and x along the direction the linear
light sensor looks ahead; with the torch down, the tool yaw (angle of tool x in the plate plane) is
``theta1 - theta5``. Horizontal reach of the tip is about 1 m (850 mm wrist reach + torch).

Matrices are plain nested tuples (row-major ``Mat4``); nothing here touches a bus or a clock.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from chcos.errors import ChcosError, ConfigError

Vec3 = tuple[float, float, float]
Row4 = tuple[float, float, float, float]
Mat4 = tuple[Row4, Row4, Row4, Row4]
Joints = tuple[float, float, float, float, float]

JOINT_NAMES: tuple[str, ...] = ("base_yaw", "shoulder", "elbow", "wrist_pitch", "torch_roll")

IDENTITY: Mat4 = (
    (1.0, 0.0, 0.0, 0.0),
    (0.0, 1.0, 0.0, 0.0),
    (0.0, 0.0, 1.0, 0.0),
    (0.0, 0.0, 0.0, 1.0),
)


class UnreachableError(ChcosError):
    """An inverse-kinematics request has no solution: the position is out of reach, directly above
    the base axis (singular), or needs a joint beyond its limits. The message names the position
    and the reason."""


@dataclass(frozen=True)
class DHLink:
    """One row of the DH table: ``d`` and ``a`` in mm, ``alpha`` in rad, joint limits in rad."""

    d: float
    a: float
    alpha: float
    lower: float
    upper: float


def dh_transform(theta: float, link: DHLink) -> Mat4:
    """The homogeneous transform of one DH link at joint angle ``theta`` (rad); lengths in mm."""
    ct, st = math.cos(theta), math.sin(theta)
    ca, sa = math.cos(link.alpha), math.sin(link.alpha)
    return (
        (ct, -st * ca, st * sa, link.a * ct),
        (st, ct * ca, -ct * sa, link.a * st),
        (0.0, sa, ca, link.d),
        (0.0, 0.0, 0.0, 1.0),
    )


def matmul(m: Mat4, n: Mat4) -> Mat4:
    """The product ``m @ n`` of two 4x4 matrices (each row summed in the order of the plain
    formula, so the result is the same to the last bit; unrolled: the arm's forward kinematics
    multiply five of them per pose, several poses per servo tick)."""
    (n00, n01, n02, n03), (n10, n11, n12, n13), (n20, n21, n22, n23), (n30, n31, n32, n33) = n
    return tuple(
        (r0 * n00 + r1 * n10 + r2 * n20 + r3 * n30,
         r0 * n01 + r1 * n11 + r2 * n21 + r3 * n31,
         r0 * n02 + r1 * n12 + r2 * n22 + r3 * n32,
         r0 * n03 + r1 * n13 + r2 * n23 + r3 * n33)
        for r0, r1, r2, r3 in m)  # type: ignore[return-value]


def translation(m: Mat4) -> Vec3:
    """The position part (mm) of a homogeneous transform."""
    return (m[0][3], m[1][3], m[2][3])


def wrap_angle(a: float) -> float:
    """``a`` (rad) wrapped into ``(-pi, pi]``."""
    w = math.fmod(a + math.pi, 2.0 * math.pi)
    if w <= 0.0:
        w += 2.0 * math.pi
    return w - math.pi


@dataclass(frozen=True)
class ToolPose:
    """Where the torch is: tip position (mm, base frame), tool yaw (rad, angle of tool x in the
    plate plane), torch tilt (rad, angle between the torch axis and straight down), and the unit
    axes of the tool frame (x: sensor look-ahead direction, z: along the torch towards the work)."""

    position: Vec3
    yaw: float
    tilt: float
    x_axis: Vec3
    z_axis: Vec3


class Arm:
    """The 5-joint welding arm with its geometry (mm) and joint limits (rad).

    Raises :class:`chcos.errors.ConfigError` if the geometry is not positive.
    """

    def __init__(
        self,
        base_height: float = 400.0,
        upper_arm: float = 450.0,
        forearm: float = 400.0,
        torch_length: float = 150.0,
        limits: Sequence[tuple[float, float]] | None = None,
    ) -> None:
        for name, value in (
            ("base_height", base_height),
            ("upper_arm", upper_arm),
            ("forearm", forearm),
            ("torch_length", torch_length),
        ):
            if not value > 0.0:
                raise ConfigError(f"arm geometry: {name}={value!r} mm, expected a positive length")
        deg = math.radians
        lims = list(
            limits
            if limits is not None
            else [
                (deg(-170), deg(170)),
                (deg(-60), deg(150)),
                (deg(-165), deg(165)),
                (deg(-170), deg(170)),
                (-math.pi, math.pi),
            ]
        )
        if len(lims) != 5 or any(not lo < hi for lo, hi in lims):
            raise ConfigError(
                f"arm limits: {lims!r}, expected 5 (lower, upper) pairs, lower < upper"
            )
        half = math.pi / 2.0
        self.base_height = base_height
        self.upper_arm = upper_arm
        self.forearm = forearm
        self.torch_length = torch_length
        self.links: tuple[DHLink, ...] = (
            DHLink(base_height, 0.0, half, *lims[0]),
            DHLink(0.0, upper_arm, 0.0, *lims[1]),
            DHLink(0.0, forearm, 0.0, *lims[2]),
            DHLink(0.0, 0.0, half, *lims[3]),
            DHLink(torch_length, 0.0, 0.0, *lims[4]),
        )

    def frames(self, q: Sequence[float]) -> tuple[Mat4, ...]:
        """T1..T5 (base frame) at joint angles ``q`` (rad).

        Raises ConfigError if ``q`` does not hold 5 angles."""
        if len(q) != 5:
            raise ConfigError(f"joint vector {tuple(q)!r}: expected 5 angles (rad)")
        out: list[Mat4] = []
        t = IDENTITY
        for theta, link in zip(q, self.links, strict=True):
            t = matmul(t, dh_transform(theta, link))
            out.append(t)
        return tuple(out)

    def forward(self, q: Sequence[float]) -> Mat4:
        """T5: the tool-tip frame (mm, base frame) at joint angles ``q`` (rad)."""
        return self.frames(q)[-1]

    def tool_pose(self, q: Sequence[float]) -> ToolPose:
        """Tip position, yaw, tilt and tool axes at joint angles ``q`` (rad)."""
        t5 = self.forward(q)
        x_axis = (t5[0][0], t5[1][0], t5[2][0])
        z_axis = (t5[0][2], t5[1][2], t5[2][2])
        tilt = math.acos(max(-1.0, min(1.0, -z_axis[2])))
        return ToolPose(translation(t5), math.atan2(x_axis[1], x_axis[0]), tilt, x_axis, z_axis)

    def within_limits(self, q: Sequence[float], tol: float = 1e-9) -> bool:
        """True if every joint angle (rad) lies inside its limits (with tolerance ``tol``)."""
        return all(
            link.lower - tol <= theta <= link.upper + tol
            for theta, link in zip(q, self.links, strict=True)
        )

    def inverse_down(self, position: Sequence[float], yaw: float = 0.0) -> Joints:
        """Joint angles (rad) that put the tip at ``position`` (x, y, z in mm, base frame) with the
        torch pointing straight down and the tool x axis at ``yaw`` (rad) in the plate plane.

        Closed form, elbow-up solution, deterministic. Raises :class:`UnreachableError` if the
        wrist centre is out of reach, directly above the base axis, or a joint limit is exceeded.
        """
        x, y, z = (float(v) for v in position)
        wz = z + self.torch_length
        r = math.hypot(x, y)
        where = f"tip position ({x:.1f}, {y:.1f}, {z:.1f}) mm"
        if r < 1e-6:
            raise UnreachableError(f"{where}: directly above the base axis (singular base yaw)")
        h = wz - self.base_height
        a2, a3 = self.upper_arm, self.forearm
        c3 = (r * r + h * h - a2 * a2 - a3 * a3) / (2.0 * a2 * a3)
        if c3 > 1.0 + 1e-12:
            raise UnreachableError(
                f"{where}: wrist centre {math.hypot(r, h):.1f} mm from the shoulder, "
                f"beyond the reach of {a2 + a3:.1f} mm"
            )
        if c3 < -1.0 - 1e-12:
            raise UnreachableError(
                f"{where}: wrist centre {math.hypot(r, h):.1f} mm from the shoulder, "
                f"closer than {abs(a2 - a3):.1f} mm"
            )
        c3 = max(-1.0, min(1.0, c3))
        theta1 = math.atan2(y, x)
        theta3 = -math.acos(c3)  # elbow up: the forearm bends down from the upper arm
        theta2 = math.atan2(h, r) + math.atan2(a3 * math.sin(-theta3), a2 + a3 * math.cos(theta3))
        theta4 = -(theta2 + theta3)
        theta5 = wrap_angle(theta1 - yaw)
        q: Joints = (theta1, theta2, theta3, theta4, theta5)
        for i, (theta, link) in enumerate(zip(q, self.links, strict=True)):
            if not link.lower - 1e-9 <= theta <= link.upper + 1e-9:
                raise UnreachableError(
                    f"{where} yaw {yaw:.3f} rad: joint {i + 1} ({JOINT_NAMES[i]}) needs "
                    f"{math.degrees(theta):.1f} deg, outside "
                    f"[{math.degrees(link.lower):.1f}, {math.degrees(link.upper):.1f}] deg"
                )
        return q
