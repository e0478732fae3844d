"""Plant blocks: coils, robot, fluid flow, spheres, camera.

The front half (field command → robot pose) is :mod:`magctl.plant.drive`,
:mod:`magctl.plant.coils` and :mod:`magctl.plant.robot`; see docs/plant-actuator.md.
"""
