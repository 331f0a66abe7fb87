"""What kind of failure an episode of a pick task was, read from the simulator state (robomimic's Lift and Can).

Every step ``OutcomeTracker.update`` reads three facts of robosuite's state: whether the gripper holds the
object (robosuite's own ``_check_grasp``), where the object is, and whether the gripper touches the scene
(the table, a bin: any geom that is neither the robot's nor an object's). From them it names, at every step,
the failure the episode would be if it ended now; the env reports that name's code as ``info["failure_kind"]``
and the evaluation records the last one of each failed episode. The kinds, first match wins:

* ever held the object:
  - ``dropped``: not holding it at the end;
  - ``lifted_timeout``: holding it at the end, lifted ``LIFTED_M`` above where it started (Can: not placed in
    its bin; Lift: not high enough);
  - ``held_not_lifted``: holding it at the end, still near where it started;
* never held it:
  - ``knocked_away``: the object moved ``KNOCKED_M`` or more across the surface from where it started, or fell
    off it;
  - ``stuck_against_table``: the gripper touched the table or bin in at least half of the last
    ``STUCK_WINDOW`` steps;
  - ``never_grasped``: none of the above (it reached, hovered or missed).

Code 0 (``none``) is a success. The thresholds are the tracker's, stated here, not tuned on any evaluation.
"""
from __future__ import annotations

import collections
from typing import Any

import numpy as np

FAILURE_KINDS = ("none", "never_grasped", "dropped", "lifted_timeout", "held_not_lifted", "knocked_away",
                 "stuck_against_table")
LIFTED_M = 0.02          # the object's height above its start that counts as lifted
KNOCKED_M = 0.05         # the object's travel across the surface, without a grasp, that counts as knocked away
FELL_M = 0.05            # below the surface it started on: it fell off
STUCK_WINDOW = 20        # last steps looked at for contact with the scene


def failure_kind_name(code: int) -> str:
    """The name of a ``info["failure_kind"]`` code (ValueError for an unknown one)."""
    if not 0 <= int(code) < len(FAILURE_KINDS):
        raise ValueError(f"unknown failure kind code {code}; known: {dict(enumerate(FAILURE_KINDS))}")
    return FAILURE_KINDS[int(code)]


def pick_object(backend: Any) -> tuple[list[str], int] | None:
    """(the object's contact geoms, its body id) for the pick tasks the tracker knows; None for other tasks."""
    name = type(backend).__name__
    if name == "Lift":
        return list(backend.cube.contact_geoms), int(backend.cube_body_id)
    if name.startswith("PickPlace") and getattr(backend, "single_object_mode", 0) == 2:
        obj = backend.objects[backend.object_id]
        return list(obj.contact_geoms), int(backend.obj_body_id[obj.name])
    return None


class OutcomeTracker:
    """One episode's facts of a pick task, updated every step; ``kind`` names the failure (module docstring)."""

    def __init__(self, backend: Any):
        self.backend = backend
        self.reset()

    def reset(self) -> None:
        """At an episode's start (robosuite may have rebuilt its model: the ids are looked up again)."""
        backend = self.backend
        self.object_geoms, self.object_body = pick_object(backend)
        model = backend.sim.model
        objects = {g for obj in getattr(backend, "objects", [getattr(backend, "cube", None)]) if obj is not None
                   for g in obj.contact_geoms}
        self._gripper_ids = {model.geom_name2id(g) for g in backend.robots[0].gripper.contact_geoms}
        self._scene_ids = {gid for gid in range(model.ngeom)
                           if not (model.geom_id2name(gid) or "").startswith(("robot", "gripper", "mount"))
                           and (model.geom_id2name(gid) or "") not in objects}
        self.start = np.array(backend.sim.data.body_xpos[self.object_body], dtype=np.float64)
        self.ever_held = self.held = False
        self.touches: collections.deque[bool] = collections.deque(maxlen=STUCK_WINDOW)

    def _touching_scene(self) -> bool:
        data = self.backend.sim.data
        for i in range(data.ncon):
            contact = data.contact[i]
            pair = (contact.geom1, contact.geom2)
            if (pair[0] in self._gripper_ids and pair[1] in self._scene_ids) or \
                    (pair[1] in self._gripper_ids and pair[0] in self._scene_ids):
                return True
        return False

    def update(self, success: bool) -> int:
        """Read this step's facts; the code of the failure the episode would be if it ended now (0: success)."""
        backend = self.backend
        self.held = bool(backend._check_grasp(gripper=backend.robots[0].gripper, object_geoms=self.object_geoms))
        self.ever_held |= self.held
        self.touches.append(self._touching_scene())
        return 0 if success else FAILURE_KINDS.index(self.kind())

    def kind(self) -> str:
        position = np.asarray(self.backend.sim.data.body_xpos[self.object_body], dtype=np.float64)
        if self.ever_held:
            if not self.held:
                return "dropped"
            return "lifted_timeout" if position[2] - self.start[2] >= LIFTED_M else "held_not_lifted"
        travel = float(np.linalg.norm(position[:2] - self.start[:2]))
        if travel >= KNOCKED_M or position[2] < self.start[2] - FELL_M:
            return "knocked_away"
        if len(self.touches) and sum(self.touches) * 2 >= STUCK_WINDOW:
            return "stuck_against_table"
        return "never_grasped"
