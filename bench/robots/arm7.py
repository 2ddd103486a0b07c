"""arm7: Gymnasium Pusher's 7-joint arm under gravity, over a table with a box on it.

State: the 7 joint angles (rad). Action: a joint-angle displacement; the position servos'
targets are ``clip(s + a)``, held for 1 s from rest, and the state is where the arm is then.
The lab's model is kinematic, ``clip(s + a)``: it ignores the sag of the finite-stiffness
servos under gravity, their torque limits, and the table and the box the arm hits.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from robot import ServoArm

XML = Path(__file__).with_name("arm7.xml")
STEP_SECONDS = 1.0


class Arm7(ServoArm):
    name = "arm7"
    description = "Gymnasium Pusher's 7-joint arm, gravity, saturated servos, table and box"
    state_names = [
        "shoulder_pan", "shoulder_lift", "upper_arm_roll", "elbow_flex",
        "forearm_roll", "wrist_flex", "wrist_roll",
    ]
    action_names = ["d_" + n for n in state_names]
    action_low = np.full(7, -0.25)
    action_high = np.full(7, 0.25)
    d_max = 0.1
    goal_components = [0, 1, 3]
    goal_radius = 0.15
    problem_distance = (0.6, 1.5)

    def __init__(self) -> None:
        self.model = mujoco.MjModel.from_xml_path(str(XML))
        self.data = mujoco.MjData(self.model)
        self.state_low = self.model.jnt_range[:, 0].copy()
        self.state_high = self.model.jnt_range[:, 1].copy()
        self.nstep = int(round(STEP_SECONDS / self.model.opt.timestep))

    def parameters(self) -> dict[str, Any]:
        return {
            "arm": "Gymnasium pusher_v5.xml's arm (link masses from density 300: upper arm ~1.6 kg, forearm ~0.8 kg)",
            "servos kp (N m/rad)": [150, 200, 60, 100, 20, 20, 10],
            "servo torque limits (N m)": [15, 10, 6, 6, 2, 2, 1],
            "obstacles": "table plane 0.325 m below the shoulder; box 0.16 x 0.16 x 0.25 m at (0.45, -0.35)",
            "step": f"target held {STEP_SECONDS} s from rest, timestep 5 ms",
        }
