"""pusher: a paddle pushing a can across a table with a rubber mat, a wet glass plate and a block.

State: the can's position ``(x, y)`` on the table (m). Action: the push ``(dx, dy)``: the paddle
is put square to the push, 1 cm behind the can, and its servos' targets move along the push at
0.25 m/s by ``|a| + 1 cm``, then hold; 1 s after the start the can's position is the next state
(the paddle is moved away between pushes). The lab's model is quasi-static, "the can moves by
the push": ``clip(s + a)``. It ignores the friction under the can (on the rubber mat the
paddle's 6 N barely move it, on the wet glass it slides on after the paddle stops, and the
3 mm edges of both catch it), the block that stops it, and the can sliding along the paddle.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from robot import Array, Robot, run_until_settled

XML = Path(__file__).with_name("pusher.xml")
STEP_SECONDS = 1.0
PUSH_SPEED = 0.25
GAP = 0.01
CAN_RADIUS = 0.04
CAN_HALF_HEIGHT = 0.03
PADDLE_HALF_THICKNESS = 0.008
SEGMENT_STEPS = 5


class Pusher(Robot):
    name = "pusher"
    description = "paddle pushing a can; rubber mat, wet glass, block"
    state_names = ["x", "y"]
    state_low = np.array([0.04, 0.04])
    state_high = np.array([0.96, 0.76])
    action_names = ["dx", "dy"]
    action_low = np.array([-0.1, -0.1])
    action_high = np.array([0.1, 0.1])
    d_max = 0.02
    goal_components = [0, 1]
    goal_radius = 0.04
    problem_distance = (0.25, 0.6)

    def __init__(self) -> None:
        self.model = mujoco.MjModel.from_xml_path(str(XML))
        self.data = mujoco.MjData(self.model)
        self.dt = float(self.model.opt.timestep)
        self.nstep = int(round(STEP_SECONDS / self.dt))

        def rect(name: str) -> tuple[Array, Array, float]:
            g = self.model.geom(name)
            return g.pos[:2] - g.size[:2], g.pos[:2] + g.size[:2], float(g.pos[2] + g.size[2])

        self.patches = [rect("mat"), rect("glass")]
        self.block = rect("block")[:2]
        self.can_q = self.model.jnt_qposadr[self.model.joint("can").id]
        self.paddle_q = self.model.jnt_qposadr[self.model.joint("px").id]

    def f_hat(self, states: Array, actions: Array) -> Array:
        return np.clip(states + actions, self.state_low, self.state_high)

    def surface(self, x: float, y: float) -> float:
        for lo, hi, top in self.patches:
            if np.all(np.array([x, y]) >= lo - CAN_RADIUS / 2) and np.all(
                np.array([x, y]) <= hi + CAN_RADIUS / 2
            ):
                return top
        return 0.0

    def true_step(self, s: Array, a: Array) -> Array:
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        x, y = float(s[0]), float(s[1])
        c = self.can_q
        d.qpos[c : c + 3] = [x, y, self.surface(x, y) + CAN_HALF_HEIGHT + 0.0005]
        d.qpos[c + 3 : c + 7] = [1, 0, 0, 0]
        dist = float(np.linalg.norm(a))
        p = self.paddle_q
        if dist < 1e-6:
            # No push: the paddle stays away.
            d.qpos[p : p + 3] = [x, y + 0.5, 0.0]
            d.ctrl[:] = d.qpos[p : p + 3]
            run_until_settled(m, d, self.nstep, 0)
        else:
            u = np.asarray(a, dtype=np.float64) / dist
            start = np.array([x, y]) - u * (CAN_RADIUS + GAP + PADDLE_HALF_THICKNESS)
            yaw = float(np.arctan2(u[1], u[0]))
            d.qpos[p : p + 3] = [start[0], start[1], yaw]
            travel = dist + GAP
            steps = 0
            while steps < self.nstep:
                k = min(SEGMENT_STEPS, self.nstep - steps)
                t = (steps + k) * self.dt
                along = min(travel, PUSH_SPEED * t)
                d.ctrl[:] = [start[0] + u[0] * along, start[1] + u[1] * along, yaw]
                mujoco.mj_step(m, d, nstep=k)
                steps += k
                if along >= travel:
                    break
            # The paddle holds its last target; the rest of the second, until all is at rest.
            run_until_settled(m, d, self.nstep - steps, 0)
        return np.clip(d.qpos[c : c + 2].copy(), self.state_low, self.state_high)

    def sample_state(self, rng: np.random.Generator) -> Array:
        lo, hi = self.block
        while True:
            s = rng.uniform(self.state_low, self.state_high)
            if not np.all((s > lo - CAN_RADIUS - 0.01) & (s < hi + CAN_RADIUS + 0.01)):
                return s

    def parameters(self) -> dict[str, Any]:
        return {
            "can": "cylinder r 0.04 m, 0.06 m high, 0.5 kg",
            "paddle": "12 cm wide, servos kp 400 N/m kv 40, |F| <= 6 N; pushes at 0.25 m/s",
            "table friction": 0.35,
            "rubber mat": "x 0.55-0.85, y 0.45-0.75, friction 1.1, 3 mm",
            "wet glass": "x 0.15-0.45, y 0.1-0.4, friction 0.05, 3 mm",
            "block": "x 0.55-0.7, y 0.1-0.3",
            "step": f"{STEP_SECONDS} s per push, timestep 4 ms",
        }
