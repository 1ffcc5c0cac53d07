"""mjxvine: vineyard-row navigation from noisy depth, trained with SAC on MuJoCo-MJX."""

from mjxvine import _quiet

__version__ = "0.2.0"

# before mujoco.mjx, absl or orbax are imported: drops their known harmless messages only
_quiet.install()
