"""mjxvine: vineyard-row navigation from noisy depth, trained with SAC on MuJoCo-MJX."""

from mjxvine import _quiet, atomic

__version__ = "0.3.0"

# before mujoco.mjx, absl or orbax are imported: drops their known harmless messages only
_quiet.install()
# `python -m mjxvine.<command>`: SIGINT / SIGTERM end it cleanly from its first import on
atomic.guard_command()
