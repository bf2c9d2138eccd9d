"""Simulator internals, used by :mod:`robo3d.simulate` (``robo3d simulate``).

- :mod:`robo3d.sim.shapes`: ground-truth objects (SDFs, marching cubes, decimation, PLY).
- :mod:`robo3d.sim.rig`: camera, hand-eye, laser mount, view rings, sweeps, robot error.
- :mod:`robo3d.sim.render`: ray-cast views and laser frames (Open3D), sensor noise.
"""
