"""base: a differential-drive robot in an arena with a mound, an icy patch and a box.

State ``(x, y, cos θ, sin θ)``: the heading is encoded by hand in :meth:`Base.encode` /
:meth:`Base.decode` (the only place that knows it). ``base_theta`` (:class:`BaseTheta`) is the
same robot with a plain heading ``θ ∈ [−π, π]`` declared periodic (``state.periodic``), as a lab
would now declare it; both draw the same poses from the same seed. Action ``(v, ω)``: forward speed and turn rate,
commanded for 1 s (the wheel speeds ``(v ∓ ω b/2) / r`` to the wheels' velocity servos), then
zero for 0.3 s to stop; the state is where the robot is then. The lab's model is the unicycle
``x' = x + ∫ v cos θ``, ``θ' = θ + ω T`` (exact arcs), clipped to the arena: it ignores the
mound's slopes (the saturated wheel torque slows the climb, the robot slides sideways across
them), the ice (the wheels slip) and the box (it stops the robot).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from robot import Array, Robot, run_until_settled

XML = Path(__file__).with_name("base.xml")
DRIVE_SECONDS = 1.0
STOP_SECONDS = 0.3
SETTLE_SECONDS = 0.1
WHEEL_RADIUS = 0.05
TRACK = 0.26
ARENA = (0.0, 3.0)
MOUND_CENTER = np.array([2.0, 2.1])
MOUND_RADIUS = 3.0
MOUND_DEPTH = 2.85  # the sphere's centre below the floor


def encode(x: Array, y: Array, theta: Array) -> Array:
    """The state vector(s) of poses: the one place that knows how the heading is encoded."""
    return np.stack([x, y, np.cos(theta), np.sin(theta)], axis=-1)


def decode(states: Array) -> tuple[Array, Array, Array]:
    """``(x, y, θ)`` of state vector(s)."""
    s = np.asarray(states)
    return s[..., 0], s[..., 1], np.arctan2(s[..., 3], s[..., 2])


def unicycle(x: Array, y: Array, th: Array, v: Array, w: Array, t: float) -> tuple[Array, Array, Array]:
    """Exact unicycle arcs over ``t`` seconds."""
    th2 = th + w * t
    small = np.abs(w) < 1e-6
    safe_w = np.where(small, 1.0, w)
    dx = np.where(small, v * t * np.cos(th), v / safe_w * (np.sin(th2) - np.sin(th)))
    dy = np.where(small, v * t * np.sin(th), -v / safe_w * (np.cos(th2) - np.cos(th)))
    return x + dx, y + dy, th2


def ground(x: float, y: float) -> tuple[float, Array]:
    """The terrain's height and unit normal at ``(x, y)``."""
    r = np.hypot(x - MOUND_CENTER[0], y - MOUND_CENTER[1])
    if r < np.sqrt(MOUND_RADIUS**2 - MOUND_DEPTH**2):
        p = np.array([x - MOUND_CENTER[0], y - MOUND_CENTER[1], 0.0])
        p[2] = np.sqrt(MOUND_RADIUS**2 - r**2)
        return float(p[2] - MOUND_DEPTH), p / MOUND_RADIUS
    return 0.0, np.array([0.0, 0.0, 1.0])


def quat_mul(a: Array, b: Array) -> Array:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ])


class Base(Robot):
    name = "base"
    description = "differential drive, mound, icy patch, hidden box"
    state_names = ["x", "y", "cos_theta", "sin_theta"]
    state_low = np.array([ARENA[0], ARENA[0], -1.0, -1.0])
    state_high = np.array([ARENA[1], ARENA[1], 1.0, 1.0])
    action_names = ["v", "omega"]
    action_low = np.array([-0.3, -1.0])
    action_high = np.array([0.3, 1.0])
    distance_weights = [1.0, 1.0, 0.04, 0.04]
    """A heading error of 1 rad counts as 0.2 m."""
    d_max = 0.05
    goal_components = [0, 1]
    goal_radius = 0.15
    problem_distance = (0.8, 2.0)

    def __init__(self) -> None:
        self.model = mujoco.MjModel.from_xml_path(str(XML))
        self.data = mujoco.MjData(self.model)
        dt = self.model.opt.timestep
        self.n_settle = int(round(SETTLE_SECONDS / dt))
        self.n_drive = int(round(DRIVE_SECONDS / dt))
        self.n_stop = int(round(STOP_SECONDS / dt))
        box = self.model.geom("box")
        self.box = (box.pos[:2] - box.size[:2], box.pos[:2] + box.size[:2])
        ice = self.model.geom("ice")
        self.ice = (ice.pos[:2] - ice.size[:2], ice.pos[:2] + ice.size[:2])
        self.ice_top = float(ice.pos[2] + ice.size[2])

    @staticmethod
    def encode(x: Array, y: Array, theta: Array) -> Array:
        return encode(x, y, theta)

    @staticmethod
    def decode(states: Array) -> tuple[Array, Array, Array]:
        return decode(states)

    def f_hat(self, states: Array, actions: Array) -> Array:
        x, y, th = self.decode(states)
        x2, y2, th2 = unicycle(x, y, th, actions[:, 0], actions[:, 1], DRIVE_SECONDS)
        x2 = np.clip(x2, *ARENA)
        y2 = np.clip(y2, *ARENA)
        return self.encode(x2, y2, th2)

    def place(self, s: Array) -> None:
        """Puts the robot at rest at pose ``s`` on the terrain."""
        m, d = self.model, self.data
        x, y, th = (float(v) for v in self.decode(s))
        mujoco.mj_resetData(m, d)
        h, n = ground(x, y)
        lo, hi = self.ice
        if lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1]:
            h = max(h, self.ice_top)
        yaw = np.array([np.cos(th / 2), 0.0, 0.0, np.sin(th / 2)])
        axis = np.cross([0.0, 0.0, 1.0], n)
        sin_a = np.linalg.norm(axis)
        if sin_a > 1e-9:
            ang = np.arcsin(min(1.0, sin_a))
            tilt = np.concatenate([[np.cos(ang / 2)], np.sin(ang / 2) * axis / sin_a])
            quat = quat_mul(tilt, yaw)
        else:
            quat = yaw
        d.qpos[:3] = [x, y, h + WHEEL_RADIUS + 0.002]
        d.qpos[3:7] = quat
        d.ctrl[:] = 0.0
        mujoco.mj_step(m, d, nstep=self.n_settle)

    def pose(self) -> Array:
        d = self.data
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, d.qpos[3:7])
        th = np.arctan2(mat[3], mat[0])  # the chassis' x-axis, seen from above
        return self.encode(np.clip(d.qpos[0], *ARENA), np.clip(d.qpos[1], *ARENA), th)

    def true_step(self, s: Array, a: Array) -> Array:
        m, d = self.model, self.data
        self.place(s)
        v, w = float(a[0]), float(a[1])
        d.ctrl[:] = [(v - w * TRACK / 2) / WHEEL_RADIUS, (v + w * TRACK / 2) / WHEEL_RADIUS]
        mujoco.mj_step(m, d, nstep=self.n_drive)
        d.ctrl[:] = 0.0
        run_until_settled(m, d, self.n_stop, 0)
        return self.pose()

    def sample_state(self, rng: np.random.Generator) -> Array:
        """A pose in the arena, the chassis clear of the box and the walls."""
        while True:
            x, y = rng.uniform(0.1, 2.9, size=2)
            lo, hi = self.box
            if np.all((np.array([x, y]) > lo - 0.25) & (np.array([x, y]) < hi + 0.25)):
                continue
            return self.encode(
                np.float64(x), np.float64(y), np.float64(rng.uniform(-np.pi, np.pi))
            )

    def parameters(self) -> dict[str, Any]:
        return {
            "chassis": "4 kg, 0.3 x 0.2 m; wheels 0.3 kg, r 0.05 m, track 0.26 m; ball caster",
            "wheel servos": "velocity, kv 2 N m s/rad, |tau| <= 0.5 N m",
            "floor friction": 0.9,
            "ice": "x 0.4-1.3, y 0.4-1.4, a 5 mm sheet, friction 0.03",
            "mound": "spherical cap 0.15 m high, base radius 0.94 m, centre (2.0, 2.1)",
            "box": "x 2.15-2.45, y 0.45-0.95, 0.2 m high",
            "step": f"drive {DRIVE_SECONDS} s, stop {STOP_SECONDS} s (after {SETTLE_SECONDS} s settling at rest), timestep 10 ms",
        }


class BaseTheta(Base):
    """The same robot, its heading a plain angle declared periodic: ``(x, y, θ)``. The lab's
    model answers ``θ + ω T`` unwrapped (the service wraps it into ``[−π, π]``); the distance
    weighs ``θ`` by 0.04 as ``Base`` weighs ``cos θ`` and ``sin θ`` (1 rad counts 0.2 m)."""

    name = "base_theta"
    description = "differential drive, mound, icy patch, hidden box; heading declared periodic"
    state_names = ["x", "y", "theta"]
    state_low = np.array([ARENA[0], ARENA[0], -np.pi])
    state_high = np.array([ARENA[1], ARENA[1], np.pi])
    distance_weights = [1.0, 1.0, 0.04]
    periodic = [2]

    @staticmethod
    def encode(x: Array, y: Array, theta: Array) -> Array:
        return np.stack([x, y, theta], axis=-1)

    @staticmethod
    def decode(states: Array) -> tuple[Array, Array, Array]:
        s = np.asarray(states)
        return s[..., 0], s[..., 1], s[..., 2]
