"""The zenoh side of bsc: samples -> estimator -> efforts; monitor -> alerts; recorder -> MCAP."""
__version__ = "0.1.0"
