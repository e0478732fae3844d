"""Plant blocks: coils, robot, fluid flow, spheres, camera."""
