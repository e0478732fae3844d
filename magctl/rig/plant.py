"""The simulated rig's plant: :func:`magctl.loops.plant` with the rig's scene and variability.

:func:`build_sim_plant` returns the diagram the rig server and :class:`~magctl.rig.sim.SimRig`
serve: exported inputs ``b_static`` (2,) T, ``b_osc`` () T, ``freq`` () 1/s — the drive's field
command — and outputs ``robot_est`` (2,) m, ``heading_est`` () rad, ``spheres_est`` (N, 2) m,
``lost`` () bool — the tracker's observation — and ``currents`` (6,) A. It is the plant of the
studies (``physics``, the default, with ``models/rig.toml`` ``[physics]`` as its variability) or
the kinematic stand-in (``standin``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from magctl.config import Params, load_model
from magctl.core.diagram import Diagram
from magctl.core.errors import WiringError
from magctl.loops import COMMAND, PLANT_OUTPUTS, PLANTS, Scene, Variability
from magctl.loops import plant as _plant

PLANT_INPUTS = COMMAND

__all__ = ["PLANTS", "PLANT_INPUTS", "PLANT_OUTPUTS", "Scene", "build_sim_plant", "check_plant"]


def build_sim_plant(n_spheres: int, scene: Scene | None = None, params: Params | None = None,
                    robot_start: Sequence[float] | None = None, plant: str = "physics", truth: bool = False) -> Diagram:
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
    plant : {"physics", "standin"}
        The physical plant blocks (default) or the fast kinematic stand-in.
    truth : bool
        Also export the true robot and sphere states (:func:`magctl.loops.plant`), for a simulated camera.
    """
    p = params or load_model("rig")
    scene = scene or Scene.default(n_spheres, p)
    if scene.spheres.shape != (n_spheres, 2):
        raise WiringError(f"scene has {scene.spheres.shape[0]} spheres but n_spheres={n_spheres}")
    if robot_start is not None:
        scene = dataclasses.replace(scene, robot=np.asarray(robot_start, dtype=float))
    diagram = _plant(scene, Variability.of_rig(p), kind=plant, truth=truth)
    if plant == "physics" and n_spheres:
        diagram.blocks["spheres"].prepare()  # flow solve and kernel compile (~1 s, once) now, not in the first frame
    return diagram


def check_plant(diagram: Diagram) -> None:
    """Raise :class:`WiringError` unless ``diagram`` exports the rig plant's ports."""
    missing_in = [n for n in PLANT_INPUTS if n not in diagram.inputs]
    missing_out = [n for n in PLANT_OUTPUTS if n not in diagram.outputs]
    if missing_in or missing_out:
        raise WiringError(
            f"plant diagram {diagram.name!r} lacks inputs {missing_in} / outputs {missing_out} "
            f"(needs inputs {list(PLANT_INPUTS)} and outputs {list(PLANT_OUTPUTS)})"
        )
