"""Writers that hand a loaded :class:`~closedchain.Mechanism` to other simulators."""

from .mjcf import MjcfSettings, export_mjcf, load_mujoco, mujoco_state

__all__ = ["MjcfSettings", "export_mjcf", "load_mujoco", "mujoco_state"]
