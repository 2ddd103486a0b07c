"""The two reference columns, with no new server code: the service's own planner over a remote
model whose ``valid`` flag says which steps may be planned, in an experiment with no data,
planned at a very negative β (before any data the prior answers μ = 0, σ = 1, so at β = −100
every step the model calls valid is trusted).

- **oracle**: ``valid`` is the lab's own check *and* the step's true deviation (MuJoCo, run
  inside the model server for every point the planner asks about) ``< d_max``: the same planner
  over the TRUE precondition.
- **baseline** (no precondition): ``valid`` is the lab's own check only: the model's own plan.
"""

from __future__ import annotations

from typing import Any

import time

import numpy as np
from numpy.typing import NDArray

from robot import Array, Robot

REFERENCE_BETA = -100.0


class ModelFns:
    """The model functions served for one robot, counting what they were asked."""

    def __init__(self, robot: Robot) -> None:
        self.robot = robot
        # The oracle simulates in the model server's thread, and a call the service has given up
        # may still run there while the bench executes plans: a MuJoCo world of its own (one
        # MjData shared by two threads corrupts both, and crashed the process once).
        self.sim = type(robot)()
        self.points = 0
        self.simulated = 0
        self.deadline: float | None = None
        """When the current reference plan's search is past the server's deadline, the server
        has given it up: the rest of its calls are answered without simulating."""
        self.skipped = 0

    def lab(self, states: Array, actions: Array) -> tuple[Array, NDArray[np.bool_]]:
        """What the learned experiment and the baseline are served: ``f̂`` and the lab's check."""
        self.points += len(states)
        return self.robot.f_hat(states, actions), self.robot.lab_valid(states, actions)

    def oracle(self, states: Array, actions: Array) -> tuple[Array, NDArray[np.bool_]]:
        """``f̂``, valid only where the lab's check passes and the true deviation is below
        ``d_max``."""
        self.points += len(states)
        nxt = self.robot.f_hat(states, actions)
        valid = self.robot.lab_valid(states, actions)
        for chunk in np.array_split(np.flatnonzero(valid), max(1, len(states) // 64)):
            if len(chunk) == 0:
                continue
            if self.deadline is not None and time.monotonic() > self.deadline:
                self.skipped += len(chunk)
                valid[chunk] = False
                continue
            true = self.sim.true_steps(states[chunk], actions[chunk])
            self.simulated += len(chunk)
            valid[chunk] = self.robot.distance(nxt[chunk], true) < self.robot.d_max
        return nxt, valid

    def stats(self) -> dict[str, Any]:
        return {"points": self.points, "simulated": self.simulated,
                "skipped_after_deadline": self.skipped}
