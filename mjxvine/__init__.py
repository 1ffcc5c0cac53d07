"""mjxvine: vineyard-row navigation from noisy depth, trained with SAC on MuJoCo-MJX."""

__version__ = "0.1.0"
