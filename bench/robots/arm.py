"""arm: a vertical 2-link arm under gravity with saturated PD servos, a shelf and a wall.

State: the two joint angles (rad; from the horizontal, up positive; the elbow relative to the
upper arm). Action: a joint-angle displacement; the servo's target is ``clip(s + a)``, held for
1 s from rest (the move and its settling), and the state is where the arm is then. The lab's
model is ``clip(s + a)``: it ignores the sag under gravity (finite stiffness), the shoulder's
torque limit (near the horizontal, stretched out, it cannot hold the arm up), and the shelf and
the wall the links hit.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from robot import ServoArm

XML = Path(__file__).with_name("arm.xml")
STEP_SECONDS = 1.0


class Arm(ServoArm):
    name = "arm"
    description = "vertical 2-link arm, gravity, saturated PD servos, shelf and wall"
    state_names = ["shoulder", "elbow"]
    state_low = np.array([-1.4, -2.2])
    state_high = np.array([1.4, 2.2])
    action_names = ["d_shoulder", "d_elbow"]
    action_low = np.array([-0.4, -0.4])
    action_high = np.array([0.4, 0.4])
    d_max = 0.07
    goal_components = [0, 1]
    goal_radius = 0.1
    problem_distance = (0.8, 2.0)

    def __init__(self) -> None:
        self.model = mujoco.MjModel.from_xml_path(str(XML))
        self.data = mujoco.MjData(self.model)
        self.nstep = int(round(STEP_SECONDS / self.model.opt.timestep))

    def parameters(self) -> dict[str, Any]:
        return {
            "links": "upper 0.4 m 2.0 kg, forearm 0.35 m 1.0 kg, hand 0.5 kg",
            "servos": "shoulder kp 150 N m/rad kv 12, |tau| <= 10 N m; elbow kp 60 kv 4, |tau| <= 5 N m",
            "gravity torque at the shoulder, stretched horizontal": "13.2 N m",
            "obstacles": "shelf top 0.25 m below the shoulder, 0.35-0.8 m in front; wall 0.45 m in front from 0.3 m above",
            "step": f"target held {STEP_SECONDS} s from rest, timestep 2 ms",
            "timestep": float(self.model.opt.timestep),
        }
