"""robo3d: measured 3D models from a robot-carried camera and line laser."""

__version__ = "0.1.0"
