"""The plant factory behind the simulated rig.

:func:`build_sim_plant` returns a :class:`~magctl.core.Diagram` with the
contract the rig server and :class:`~magctl.rig.sim.SimRig` rely on:

* exported inputs ``b_static`` (2,) T, ``b_osc`` () T, ``freq`` () 1/s — the drive's field command;
* exported outputs ``robot_est`` (2,) m, ``heading_est`` () rad, ``spheres_est`` (N, 2) m,
  ``lost`` () bool — the tracker's observation — and ``currents`` (6,) A.

Today the diagram is made of the kinematic stand-in blocks of
:mod:`magctl.rig.standin`; at integration the coil, robot, sphere, camera and
tracker blocks of ``magctl.plant`` / ``magctl.control.tracker`` replace them
behind the same exported ports.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from magctl.config import Params, load_model
from magctl.core.diagram import Diagram
from magctl.core.errors import WiringError
from magctl.plant.robot import load_robot
from magctl.rig.interface import CoilMap
from magctl.rig.standin import StandinCoils, StandinRobot, StandinSpheres, StandinTracker

PLANT_INPUTS = ("b_static", "b_osc", "freq")
PLANT_OUTPUTS = ("robot_est", "heading_est", "spheres_est", "lost", "currents")


@dataclass
class Scene:
    """Initial layout of a simulated rig (SI).

    Attributes
    ----------
    robot : (2,) array
        Robot start position, m.
    heading : float
        Robot start heading, rad.
    spheres : (N, 2) array
        Sphere centres, m.
    blackout : (float, float) or None
        Window ``[t0, t1)`` in s of forced tracking loss (for tests of loss handling).
    """

    robot: np.ndarray = field(default_factory=lambda: np.zeros(2))
    heading: float = 0.0
    spheres: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    blackout: tuple[float, float] | None = None

    @classmethod
    def default(cls, n_spheres: int, params: Params | None = None, **kw) -> Scene:
        """Robot at the origin heading +x, spheres on the +x axis every ``standin.sphere_spacing``.

        This is the starting layout of the paper's experiments (§VI): the robot 1 mm from the sphere.
        """
        if n_spheres < 0:
            raise WiringError(f"n_spheres must be >= 0, got {n_spheres}")
        p = params or load_model("rig")
        gap = p.standin.sphere_spacing
        spheres = np.array([[gap * (i + 1), 0.0] for i in range(n_spheres)]).reshape(-1, 2)
        return cls(spheres=spheres, **kw)

    def to_dict(self) -> dict:
        return {"robot_um": (self.robot * 1e6).tolist(), "heading_rad": self.heading,
                "spheres_um": (self.spheres * 1e6).tolist(),
                "blackout_s": None if self.blackout is None else list(self.blackout)}


def build_sim_plant(n_spheres: int, scene: Scene | None = None, params: Params | None = None,
                    robot_start: Sequence[float] | None = None) -> Diagram:
    """The simulated rig's plant: field command in, tracker observation out.

    Parameters
    ----------
    n_spheres : int
        Number of spheres in the scene (the length of ``spheres_est``).
    scene : Scene, optional
        Initial layout; :meth:`Scene.default` when omitted.
    params : Params, optional
        ``models/rig.toml`` (loaded when omitted).
    robot_start : (2,) sequence, optional
        Overrides ``scene.robot``.

    Returns
    -------
    Diagram
        Inputs ``b_static``, ``b_osc``, ``freq``; outputs ``robot_est``, ``heading_est``,
        ``spheres_est``, ``lost``, ``currents``.
    """
    p = params or load_model("rig")
    scene = scene or Scene.default(n_spheres, p)
    if scene.spheres.shape != (n_spheres, 2):
        raise WiringError(f"scene has {scene.spheres.shape[0]} spheres but n_spheres={n_spheres}")
    start = scene.robot if robot_start is None else np.asarray(robot_start, dtype=float)
    sd = p.standin
    coils = StandinCoils("coils", CoilMap.from_params(p.coils))
    robot = StandinRobot("robot", load_robot(), start, scene.heading)
    spheres = StandinSpheres("spheres", scene.spheres, sd.robot_contact_radius + sd.sphere_radius,
                             release_mean=sd.release_mean, release_std=sd.release_std, side_range=sd.side_range,
                             start_robot=start)
    tracker = StandinTracker("tracker", n_spheres, sd.workspace_half, scene.blackout, start, scene.heading,
                             scene.spheres)
    return Diagram(
        "sim_plant",
        [coils, robot, spheres, tracker],
        connections=[
            ("coils.b_static_delivered", "robot.b_static_delivered"),
            ("coils.b_osc_delivered", "robot.b_osc_delivered"),
            ("coils.freq_delivered", "robot.freq_delivered"),
            ("robot.position", "spheres.position"),
            ("robot.heading", "spheres.heading"),
            ("robot.velocity", "spheres.velocity"),
            ("robot.position", "tracker.position"),
            ("robot.heading", "tracker.heading"),
            ("spheres.spheres", "tracker.spheres"),
        ],
        inputs={"b_static": "coils.b_static", "b_osc": "coils.b_osc", "freq": "coils.freq"},
        outputs={"robot_est": "tracker.robot_est", "heading_est": "tracker.heading_est",
                 "spheres_est": "tracker.spheres_est", "lost": "tracker.lost", "currents": "coils.currents"},
    )


def check_plant(diagram: Diagram) -> None:
    """Raise :class:`WiringError` unless ``diagram`` exports the rig plant's ports."""
    missing_in = [n for n in PLANT_INPUTS if n not in diagram.inputs]
    missing_out = [n for n in PLANT_OUTPUTS if n not in diagram.outputs]
    if missing_in or missing_out:
        raise WiringError(
            f"plant diagram {diagram.name!r} lacks inputs {missing_in} / outputs {missing_out} "
            f"(needs inputs {list(PLANT_INPUTS)} and outputs {list(PLANT_OUTPUTS)})"
        )
